/* The run log's rows as CSV text, in C: the compiled build's row formatter.
 *
 * mrctl/runlog/rowtext.py is the interface and the reference: every value is
 * written exactly as Python's '%.<P>g' % value writes it (the formats of
 * mrctl/runlog/format.py are the log's contract), so the compiled and the
 * interpreted builds write the same bytes (tests/test_rowtext.py).
 *
 * Why C: Python's '%' costs ~0.2 us a value in object handling around the
 * conversion, and the log is 15 values a tick. Here a value costs tens of ns:
 *
 *   - NaN, +-inf, +-0 and integers below 10^P are written directly;
 *   - any other value is scaled by an exact power of ten (10^0..10^22) with
 *     one correctly rounded multiply or divide, so the scaled value is within
 *     half an ulp of the exact one; rounded to P digits it is the exact
 *     answer unless it lies within a few ulps of a tie (...5 exactly), and
 *     then, or out of that range (|x| < ~1e-14 or > ~1e30), or for P > 12,
 *     the value goes to the C library's snprintf where that is known to be
 *     correctly rounded (glibc), else to CPython's own PyOS_double_to_string,
 *     which is what '%' calls: correct by construction, rare by design.
 *
 * The GIL: the caller chooses. The daemon's loop thread formats a few rows
 * in its idle time and keeps the GIL (handing it over can cost a cross-CPU
 * wake-up inside a tick: docs/design.md, "Threads"); a writer thread
 * releases it for the whole block, taking it back only for a value that
 * needs CPython's conversion (none with glibc). mrctl simulate's block writer formats and
 * write(2)s a block in one call without the GIL (write_columns): the
 * compiled loop beside it holds the GIL for a whole block, and a writer that
 * needed it between formatting and writing would wait for that block.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>
#include <errno.h>
#include <unistd.h>

#define MAX_PREC 17       /* integers up to 10^17 < 2^63 */
#define MAX_FAST_PREC 12  /* scaled values < 10^12 < 2^40: ulps far below the tie margin */
#define MAX_VALUE_CHARS 26 /* '-', 17 digits, '.', 'e-308', and the separator */

static const double POW10[23] = {
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11,
    1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22};

static const uint64_t IPOW10[19] = {
    1ULL, 10ULL, 100ULL, 1000ULL, 10000ULL, 100000ULL, 1000000ULL, 10000000ULL,
    100000000ULL, 1000000000ULL, 10000000000ULL, 100000000000ULL,
    1000000000000ULL, 10000000000000ULL, 100000000000000ULL,
    1000000000000000ULL, 10000000000000000ULL, 100000000000000000ULL,
    1000000000000000000ULL};

static const char DIGITS2[] =
    "00010203040506070809101112131415161718192021222324252627282930313233343536373839"
    "40414243444546474849505152535455565758596061626364656667686970717273747576777879"
    "8081828384858687888990919293949596979899";

/* the decimal digits of v, exactly n of them (leading zeros), ending at end */
static void put_digits(char *end, uint64_t v, int n)
{
    while (n >= 2) {
        unsigned r = (unsigned)(v % 100);
        v /= 100;
        end -= 2;
        memcpy(end, DIGITS2 + 2 * r, 2);
        n -= 2;
    }
    if (n)
        *--end = (char)('0' + (int)(v % 10));
}

static int count_digits(uint64_t v)
{
    int n = 1;
    while (n < 19 && v >= IPOW10[n])
        n++;
    return n;
}

static char *put_uint(char *p, uint64_t v)
{
    int n = count_digits(v);
    put_digits(p + n, v, n);
    return p + n;
}

/* x as '%.<prec>g' writes it, at p; the end of the text, or NULL when only
 * CPython's conversion can tell (then nothing is written that counts). */
static char *fmt_g(char *p, double x, int prec)
{
    if (isnan(x)) {  /* '%g' writes every NaN as 'nan', whatever its sign */
        memcpy(p, "nan", 3);
        return p + 3;
    }
    if (signbit(x)) {
        *p++ = '-';
        x = -x;
    }
    if (isinf(x)) {
        memcpy(p, "inf", 3);
        return p + 3;
    }
    if (x == 0.0) {
        *p++ = '0';
        return p;
    }
    if (x < POW10[prec] && (double)(uint64_t)x == x)  /* an integer of at most prec digits: written whole */
        return put_uint(p, (uint64_t)x);
    if (prec > MAX_FAST_PREC)
        return NULL;

    uint64_t bits;
    memcpy(&bits, &x, sizeof bits);
    int e2 = (int)((bits >> 52) & 0x7ff) - 1023;  /* 2^e2 <= x < 2^(e2+1) (x normal) */
    if (e2 < -200 || e2 > 200)  /* far out of the exact powers' reach anyway; subnormals too */
        return NULL;
    /* floor(e2 log10 2): log10(x) is this or one more; the scaled value tells which */
    int e10 = e2 >= 0 ? (e2 * 78913) >> 18 : -((-e2 * 78913 + (1 << 18) - 1) >> 18);
    uint64_t d = 0;
    const double lo = POW10[prec - 1], hi = POW10[prec];
    for (int attempt = 0;; attempt++) {
        int s = prec - 1 - e10;
        if (s > 22 || s < -22)
            return NULL;
        double y = s >= 0 ? x * POW10[s] : x / POW10[-s];  /* one rounding: within half an ulp */
        if (attempt == 0 && y < lo) {  /* (never, from the estimate above; kept for safety) */
            e10--;
            continue;
        }
        if (attempt == 0 && y >= hi) {
            e10++;
            continue;
        }
        double whole = (double)(uint64_t)y, frac = y - whole;  /* exact: 0 < y < 2^53 */
        if (fabs(frac - 0.5) <= y * 0x1p-50)  /* a tie, or too close to one to tell */
            return NULL;
        d = (uint64_t)whole + (frac > 0.5 ? 1u : 0u);
        break;
    }
    if (d == IPOW10[prec]) {  /* 9.99..95 rounds up to the next power of ten */
        d = IPOW10[prec - 1];
        e10++;
    } else if (d > IPOW10[prec] || d < IPOW10[prec - 1]) {
        return NULL;
    }

    char dig[MAX_PREC + 1];
    put_digits(dig + prec, d, prec);
    int nd = prec;
    while (nd > 1 && dig[nd - 1] == '0')
        nd--;
    if (e10 < -4 || e10 >= prec) {  /* d.ddde+XX, at least two exponent digits */
        *p++ = dig[0];
        if (nd > 1) {
            *p++ = '.';
            memcpy(p, dig + 1, (size_t)(nd - 1));
            p += nd - 1;
        }
        *p++ = 'e';
        *p++ = e10 < 0 ? '-' : '+';
        int ae = e10 < 0 ? -e10 : e10;
        if (ae < 10)
            *p++ = '0';
        return put_uint(p, (uint64_t)ae);
    }
    if (e10 >= 0) {
        int whole = e10 + 1;
        if (nd <= whole) {
            memcpy(p, dig, (size_t)nd);
            p += nd;
            memset(p, '0', (size_t)(whole - nd));
            return p + (whole - nd);
        }
        memcpy(p, dig, (size_t)whole);
        p += whole;
        *p++ = '.';
        memcpy(p, dig + whole, (size_t)(nd - whole));
        return p + (nd - whole);
    }
    *p++ = '0';
    *p++ = '.';
    memset(p, '0', (size_t)(-e10 - 1));
    p += -e10 - 1;
    memcpy(p, dig, (size_t)nd);
    return p + nd;
}

typedef struct {
    const char *base;   /* the value of row 0 */
    Py_ssize_t stride;  /* bytes from one row to the next */
} Column;

/* The C library's conversion of one value, without the GIL, where it is known
 * to be what '%' writes: glibc's printf converts every double correctly
 * rounded (ties to even, as CPython's dtoa), and '%g' is '%g' in both.
 * The text is checked to hold only what '%g' writes in the C locale (a
 * locale whose decimal point is not '.' fails the check). The end, or NULL
 * when only CPython's conversion can tell. Why: the rare values (a sine's
 * zero crossing, ~1e-18, on every cycle) would otherwise take the GIL back,
 * and mrctl simulate's compiled loop holds it for a whole block. */
static char *fmt_g_libc(char *p, double x, int prec)
{
#if defined(__GLIBC__)
    char buf[MAX_VALUE_CHARS + 8];
    int n = snprintf(buf, sizeof buf, "%.*g", prec, x);
    if (n <= 0 || n > MAX_VALUE_CHARS - 1)
        return NULL;
    for (int i = 0; i < n; i++) {
        char c = buf[i];
        if (!((c >= '0' && c <= '9') || c == '.' || c == 'e' || c == '-' || c == '+'))
            return NULL;
    }
    memcpy(p, buf, (size_t)n);
    return p + n;
#else
    (void)p;
    (void)x;
    (void)prec;
    return NULL;
#endif
}

/* CPython's conversion of one value (needs the GIL); the end, or NULL with an exception set. */
static char *fmt_g_cpython(char *p, double x, int prec)
{
    char *s = PyOS_double_to_string(x, 'g', prec, 0, NULL);
    if (s == NULL)
        return NULL;
    size_t n = strlen(s);
    if (n > MAX_VALUE_CHARS - 1) {
        PyMem_Free(s);
        PyErr_SetString(PyExc_SystemError, "rowtext: a value longer than expected");
        return NULL;
    }
    memcpy(p, s, n);
    PyMem_Free(s);
    return p + n;
}

/* The rows as CSV text at p; the end, or NULL with an exception set. With
 * *ts not NULL the GIL is released, and it is taken back (and released
 * again) around CPython's conversion of the rare value that needs it; on
 * failure the GIL is held and *ts is NULL. */
static char *format_into(char *p, const Column *cols, const int *prec, int ncols, Py_ssize_t row0,
                         Py_ssize_t nrows, PyThreadState **ts)
{
    for (Py_ssize_t r = row0; r < row0 + nrows; r++) {
        for (int j = 0; j < ncols; j++) {
            double x;
            memcpy(&x, cols[j].base + r * cols[j].stride, sizeof x);
            char *q = fmt_g(p, x, prec[j]);
            if (q == NULL)
                q = fmt_g_libc(p, x, prec[j]);
            if (q == NULL) {
                if (*ts != NULL)
                    PyEval_RestoreThread(*ts);
                q = fmt_g_cpython(p, x, prec[j]);
                if (q == NULL) {
                    *ts = NULL;
                    return NULL;
                }
                if (*ts != NULL)
                    *ts = PyEval_SaveThread();
            }
            p = q;
            *p++ = j + 1 < ncols ? ',' : '\n';
        }
    }
    return p;
}

static Py_ssize_t text_capacity(int ncols, Py_ssize_t nrows)
{
    if (nrows > (PY_SSIZE_T_MAX - 1) / ((Py_ssize_t)ncols * MAX_VALUE_CHARS + 1)) {
        PyErr_SetString(PyExc_OverflowError, "rowtext: too many rows for one call");
        return -1;
    }
    return nrows * ((Py_ssize_t)ncols * MAX_VALUE_CHARS + 1);
}

static PyObject *format_table(const Column *cols, const int *prec, int ncols, Py_ssize_t row0,
                              Py_ssize_t nrows, int release)
{
    Py_ssize_t cap = text_capacity(ncols, nrows);
    if (cap < 0)
        return NULL;
    PyObject *out = PyBytes_FromStringAndSize(NULL, cap);
    if (out == NULL)
        return NULL;
    char *start = PyBytes_AS_STRING(out);
    PyThreadState *ts = release ? PyEval_SaveThread() : NULL;
    char *end = format_into(start, cols, prec, ncols, row0, nrows, &ts);
    if (ts != NULL)
        PyEval_RestoreThread(ts);
    if (end == NULL) {
        Py_DECREF(out);
        return NULL;
    }
    if (_PyBytes_Resize(&out, end - start) < 0)
        return NULL;
    return out;
}

/* Format and write(2) to fd, all without the GIL (but for the rare value
 * CPython converts); (bytes written, complete lines written, errno or 0). */
static PyObject *write_table(int fd, const Column *cols, const int *prec, int ncols, Py_ssize_t row0,
                             Py_ssize_t nrows)
{
    Py_ssize_t cap = text_capacity(ncols, nrows);
    if (cap < 0)
        return NULL;
    char *start = PyMem_RawMalloc(cap > 0 ? (size_t)cap : 1);
    if (start == NULL)
        return PyErr_NoMemory();
    PyThreadState *ts = PyEval_SaveThread();
    char *end = format_into(start, cols, prec, ncols, row0, nrows, &ts);
    Py_ssize_t done = 0, lines = nrows;
    int err = 0;
    if (end != NULL) {
        Py_ssize_t len = end - start;
        while (done < len) {
            ssize_t k = write(fd, start + done, (size_t)(len - done));
            if (k < 0 && errno == EINTR)
                continue;
            if (k <= 0) {
                err = k < 0 ? errno : EIO;
                break;
            }
            done += k;
        }
        if (err) {  /* a partial write keeps its complete lines */
            lines = 0;
            for (Py_ssize_t i = 0; i < done; i++)
                lines += start[i] == '\n';
        }
    }
    if (ts != NULL)
        PyEval_RestoreThread(ts);
    PyMem_RawFree(start);
    if (end == NULL)
        return NULL;
    return Py_BuildValue("nni", done, lines, err);
}

/* precisions: a sequence of ints in [1, MAX_PREC], one per column. */
static int read_precisions(PyObject *seq, int *prec, int ncols)
{
    PyObject *fast = PySequence_Fast(seq, "rowtext: precisions must be a sequence of ints");
    if (fast == NULL)
        return -1;
    if (PySequence_Fast_GET_SIZE(fast) != ncols) {
        PyErr_Format(PyExc_ValueError, "rowtext: %d columns but %zd precisions", ncols,
                     PySequence_Fast_GET_SIZE(fast));
        Py_DECREF(fast);
        return -1;
    }
    for (int j = 0; j < ncols; j++) {
        long v = PyLong_AsLong(PySequence_Fast_GET_ITEM(fast, j));
        if (v == -1 && PyErr_Occurred()) {
            Py_DECREF(fast);
            return -1;
        }
        if (v < 1 || v > MAX_PREC) {
            PyErr_Format(PyExc_ValueError, "rowtext: precision %ld outside 1..%d", v, MAX_PREC);
            Py_DECREF(fast);
            return -1;
        }
        prec[j] = (int)v;
    }
    Py_DECREF(fast);
    return 0;
}

/* A contiguous buffer of native doubles (array('d'), a float64 ndarray, a
 * packed block); its length in doubles, or -1 with an exception set. */
static Py_ssize_t get_doubles(PyObject *obj, Py_buffer *view)
{
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    const char *f = view->format ? view->format : "B";
    if (*f == '@' || *f == '=' || *f == '<')  /* native order on the machines mrctl builds on */
        f++;
    if (strcmp(f, "d") != 0 || view->itemsize != 8) {
        PyErr_Format(PyExc_TypeError, "rowtext: need a buffer of float64, got format '%s'",
                     view->format ? view->format : "B");
        PyBuffer_Release(view);
        return -1;
    }
    return view->len / 8;
}

static int check_rows(Py_ssize_t row0, Py_ssize_t nrows, Py_ssize_t have)
{
    if (row0 < 0 || nrows < 0 || row0 > have || nrows > have - row0) {
        PyErr_Format(PyExc_IndexError, "rowtext: rows %zd..%zd outside the %zd rows given", row0,
                     row0 + nrows, have);
        return -1;
    }
    return 0;
}

static PyObject *rowtext_format_rows(PyObject *module, PyObject *args)
{
    PyObject *buf, *precs;
    Py_ssize_t row0, nrows;
    int release = 0;
    (void)module;
    if (!PyArg_ParseTuple(args, "OOnn|p:format_rows", &buf, &precs, &row0, &nrows, &release))
        return NULL;
    Py_ssize_t ncols = PyObject_Length(precs);
    if (ncols < 0)
        return NULL;
    if (ncols < 1 || ncols > 1024) {
        PyErr_SetString(PyExc_ValueError, "rowtext: 1 to 1024 columns");
        return NULL;
    }
    int prec[1024];
    Column cols[1024];
    if (read_precisions(precs, prec, (int)ncols) < 0)
        return NULL;
    Py_buffer view;
    Py_ssize_t n = get_doubles(buf, &view);
    if (n < 0)
        return NULL;
    PyObject *out = NULL;
    if (check_rows(row0, nrows, n / ncols) == 0) {
        for (Py_ssize_t j = 0; j < ncols; j++) {
            cols[j].base = (const char *)view.buf + 8 * j;
            cols[j].stride = 8 * ncols;
        }
        out = format_table(cols, prec, (int)ncols, row0, nrows, release);
    }
    PyBuffer_Release(&view);
    return out;
}

/* format_columns and write_columns: columns (a sequence of float64 buffers),
 * precisions, row0, nrows; then release (format) or fd (write). */
static PyObject *columns_call(PyObject *seq, PyObject *precs, Py_ssize_t row0, Py_ssize_t nrows, int release,
                              int fd)
{
    PyObject *fast = PySequence_Fast(seq, "rowtext: columns must be a sequence of buffers");
    if (fast == NULL)
        return NULL;
    Py_ssize_t ncols = PySequence_Fast_GET_SIZE(fast);
    if (ncols < 1 || ncols > 1024) {
        Py_DECREF(fast);
        PyErr_SetString(PyExc_ValueError, "rowtext: 1 to 1024 columns");
        return NULL;
    }
    int prec[1024];
    Column cols[1024];
    Py_buffer *views = PyMem_Calloc((size_t)ncols, sizeof(Py_buffer));
    PyObject *out = NULL;
    Py_ssize_t got = 0;
    if (views == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    if (read_precisions(precs, prec, (int)ncols) < 0)
        goto done;
    for (; got < ncols; got++) {
        Py_ssize_t n = get_doubles(PySequence_Fast_GET_ITEM(fast, got), &views[got]);
        if (n < 0 || check_rows(row0, nrows, n) < 0) {
            if (n >= 0)
                got++;  /* release this one too */
            goto done;
        }
        cols[got].base = (const char *)views[got].buf;
        cols[got].stride = 8;
    }
    out = fd < 0 ? format_table(cols, prec, (int)ncols, row0, nrows, release)
                 : write_table(fd, cols, prec, (int)ncols, row0, nrows);
done:
    for (Py_ssize_t j = 0; j < got; j++)
        PyBuffer_Release(&views[j]);
    PyMem_Free(views);
    Py_DECREF(fast);
    return out;
}

static PyObject *rowtext_format_columns(PyObject *module, PyObject *args)
{
    PyObject *seq, *precs;
    Py_ssize_t row0, nrows;
    int release = 0;
    (void)module;
    if (!PyArg_ParseTuple(args, "OOnn|p:format_columns", &seq, &precs, &row0, &nrows, &release))
        return NULL;
    return columns_call(seq, precs, row0, nrows, release, -1);
}

static PyObject *rowtext_write_columns(PyObject *module, PyObject *args)
{
    PyObject *seq, *precs;
    Py_ssize_t row0, nrows;
    int fd;
    (void)module;
    if (!PyArg_ParseTuple(args, "iOOnn:write_columns", &fd, &seq, &precs, &row0, &nrows))
        return NULL;
    if (fd < 0) {
        PyErr_SetString(PyExc_ValueError, "rowtext: a negative file descriptor");
        return NULL;
    }
    return columns_call(seq, precs, row0, nrows, 0, fd);
}

static PyMethodDef rowtext_methods[] = {
    {"format_rows", rowtext_format_rows, METH_VARARGS,
     "format_rows(buf, precisions, row0, nrows, release_gil=False) -> bytes\n\n"
     "Rows row0..row0+nrows of a row-major buffer of float64 (len(precisions) per row) as CSV\n"
     "lines, each value as '%.<P>g' % value writes it."},
    {"format_columns", rowtext_format_columns, METH_VARARGS,
     "format_columns(columns, precisions, row0, nrows, release_gil=False) -> bytes\n\n"
     "The same for a sequence of float64 column buffers."},
    {"write_columns", rowtext_write_columns, METH_VARARGS,
     "write_columns(fd, columns, precisions, row0, nrows) -> (bytes written, lines written, errno)\n\n"
     "format_columns' text written to the file descriptor fd, all without the GIL; errno 0 when\n"
     "everything was written."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef rowtext_module = {PyModuleDef_HEAD_INIT, "_rowtext",
                                            "The run log's compiled row formatter (see rowtext.py).",
                                            -1, rowtext_methods};

PyMODINIT_FUNC PyInit__rowtext(void) { return PyModule_Create(&rowtext_module); }
