// Host build of the reference firmware: the same protocol core (firmware/core)
// with the Teensy board's calibration (board_config.h), serving a pty instead
// of USB serial and reading a simulated sensor source (sim_source.h) instead of
// the ADC, so `mrctl run` can talk to it like to the board.
//
//   g++ -std=c++17 -O2 -Wall -Wextra -Werror -Ifirmware/core
//       -Ifirmware/boards/teensy4/mrctl_teensy4 firmware/core/*.cpp
//       firmware/host/mrctl_fw_host.cpp -o /tmp/mrctl_fw_host      (one line)
//   /tmp/mrctl_fw_host --link /tmp/mrctl-fw-tty --rate-hz 1000
//
// The sampling tick runs on CLOCK_MONOTONIC deadlines (the board's hardware
// timer); between ticks the program waits in ppoll() on the pty. One thread:
// receive, tick and poll run in one context, as on the board. Prints a READY
// line on stdout once the link is up, and a summary line on exit (SIGTERM,
// SIGINT or --duration-s).
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <string>

#include "board_config.h"
#include "mrctl_device.h"
#include "sim_source.h"

namespace {

volatile sig_atomic_t g_stop = 0;
void on_signal(int) { g_stop = 1; }

int64_t mono_ns() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1000000000LL + ts.tv_nsec;
}

class PtyIo : public mrctl_fw::DeviceIo {
 public:
  int fd = -1;
  uint32_t tx_dropped = 0;  // bytes the pty had no room for (the host stopped reading)
  uint32_t output_counts = 0;
  bool output_enable = false;
  bool estop = false;  // the E-stop input (the --estop-at-s window)

  void send(const uint8_t* data, size_t n) override {
    while (n > 0) {
      const ssize_t w = write(fd, data, n);
      if (w < 0 && errno == EINTR) continue;
      if (w <= 0) {
        tx_dropped += static_cast<uint32_t>(n);
        return;
      }
      data += w;
      n -= static_cast<size_t>(w);
    }
  }
  void set_output(uint32_t counts, bool enable) override {
    output_counts = counts;
    output_enable = enable;
  }
  bool estop_open() override { return estop; }
};

struct Args {
  std::string link;
  double rate_hz = board::kSampleRateHz;
  double duration_s = 0;  // 0 = until SIGTERM/SIGINT
  host::SimParams sim;
  bool load_cell = true;
  double velocity_cutoff_hz = -1;  // < 0: the board's
  double estop_at_s = -1;  // the E-stop input opens at this device time (s); < 0: never
  double estop_for_s = 0;  // ... for this long
};

[[noreturn]] void usage(const char* msg) {
  fprintf(stderr,
          "mrctl_fw_host: %s\n"
          "usage: mrctl_fw_host --link PATH [--rate-hz HZ] [--duration-s S] [--amplitude-m M]\n"
          "       [--frequency-hz HZ] [--tau-s S] [--no-load-cell] [--velocity-cutoff-hz HZ]\n"
          "       [--estop-at-s S --estop-for-s S]\n",
          msg);
  exit(2);
}

double number(const char* name, const char* text, double lo, double hi) {
  char* end = nullptr;
  const double v = strtod(text, &end);
  if (end == text || *end != '\0' || !(v >= lo && v <= hi)) {
    fprintf(stderr, "mrctl_fw_host: %s must be a number in [%g, %g], got '%s'\n", name, lo, hi, text);
    exit(2);
  }
  return v;
}

Args parse(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    if (k == "--no-load-cell") {
      a.load_cell = false;
      continue;
    }
    if (i + 1 >= argc) usage(("missing value after " + k).c_str());
    const char* v = argv[++i];
    if (k == "--link") a.link = v;
    else if (k == "--rate-hz") a.rate_hz = number("--rate-hz", v, 1, 20000);
    else if (k == "--duration-s") a.duration_s = number("--duration-s", v, 0, 1e7);
    else if (k == "--amplitude-m") a.sim.amplitude_m = number("--amplitude-m", v, 0, 0.02);
    else if (k == "--frequency-hz") a.sim.frequency_hz = number("--frequency-hz", v, 0, 100);
    else if (k == "--tau-s") a.sim.tau_s = number("--tau-s", v, 0, 1);
    else if (k == "--velocity-cutoff-hz") a.velocity_cutoff_hz = number("--velocity-cutoff-hz", v, 0, 10000);
    else if (k == "--estop-at-s") a.estop_at_s = number("--estop-at-s", v, 0, 1e7);
    else if (k == "--estop-for-s") a.estop_for_s = number("--estop-for-s", v, 0, 1e7);
    else usage(("unknown option " + k).c_str());
  }
  if (a.link.empty()) usage("--link PATH is required");
  return a;
}

// A pty whose device end we serve; its host end is symlinked at `link` (as
// hil_sim does), and kept open here so the host may close and reopen it.
int open_pty(const std::string& link, int* slave_out, std::string* tty_out) {
  const int master = posix_openpt(O_RDWR | O_NOCTTY);
  if (master < 0 || grantpt(master) != 0 || unlockpt(master) != 0) return -1;
  const char* name = ptsname(master);
  if (!name) return -1;
  const int slave = open(name, O_RDWR | O_NOCTTY);
  if (slave < 0) return -1;
  termios t;
  if (tcgetattr(slave, &t) == 0) {
    cfmakeraw(&t);
    tcsetattr(slave, TCSANOW, &t);
  }
  const std::string tmp = link + ".tmp";
  unlink(tmp.c_str());
  if (symlink(name, tmp.c_str()) != 0 || rename(tmp.c_str(), link.c_str()) != 0) return -1;
  fcntl(master, F_SETFL, fcntl(master, F_GETFL) | O_NONBLOCK);
  *slave_out = slave;
  *tty_out = name;
  return master;
}

}  // namespace

int main(int argc, char** argv) {
  const Args args = parse(argc, argv);
  mrctl_fw::DeviceConfig cfg = board::kDeviceConfig;
  cfg.sample_period_s = static_cast<float>(1.0 / args.rate_hz);
  cfg.has_load_cell = args.load_cell;
  if (args.velocity_cutoff_hz >= 0) cfg.velocity_cutoff_hz = static_cast<float>(args.velocity_cutoff_hz);

  int slave = -1;
  std::string tty;
  PtyIo io;
  io.fd = open_pty(args.link, &slave, &tty);
  if (io.fd < 0) {
    fprintf(stderr, "mrctl_fw_host: cannot create a pty at %s: %s\n", args.link.c_str(), strerror(errno));
    return 3;
  }
  struct sigaction sa = {};
  sa.sa_handler = on_signal;
  sigaction(SIGTERM, &sa, nullptr);
  sigaction(SIGINT, &sa, nullptr);

  mrctl_fw::Device device(cfg, io);
  host::SimSource source(args.sim, cfg);
  const int64_t period_ns = static_cast<int64_t>(1e9 / args.rate_hz + 0.5);
  const int64_t t0 = mono_ns();
  const int64_t t_end = args.duration_s > 0 ? t0 + static_cast<int64_t>(args.duration_s * 1e9) : INT64_MAX;
  int64_t k = 0;  // index of the next tick
  uint64_t late_ticks = 0;
  auto dev_us = [t0](int64_t t_ns) { return static_cast<uint32_t>((t_ns - t0) / 1000); };

  printf("mrctl_fw_host ready tty=%s link=%s rate_hz=%g load_cell=%d\n", tty.c_str(), args.link.c_str(),
         args.rate_hz, args.load_cell ? 1 : 0);
  fflush(stdout);

  uint8_t buf[256];
  while (!g_stop) {
    int64_t now = mono_ns();
    if (now >= t_end) break;
    const int64_t due = t0 + k * period_ns;
    if (now >= due) {
      // the tick at k·period (the sample clock); ticks this process was too late
      // for are skipped and counted, as a board's timer never would
      const int64_t k_now = (now - t0) / period_ns;
      if (k_now > k) late_ticks += static_cast<uint64_t>(k_now - k);
      k = k_now;
      const int64_t t_tick = t0 + k * period_ns;
      const double t_s = static_cast<double>(k * period_ns) * 1e-9;
      io.estop = args.estop_at_s >= 0 && t_s >= args.estop_at_s && t_s < args.estop_at_s + args.estop_for_s;
      device.tick(source.sample(t_s, device.applied_A()), dev_us(t_tick));
      ++k;
    }
    now = mono_ns();
    device.poll(dev_us(now));
    const int64_t wait_ns = t0 + k * period_ns - now;
    if (wait_ns <= 0) continue;
    pollfd pfd = {io.fd, POLLIN, 0};
    const timespec ts = {static_cast<time_t>(wait_ns / 1000000000LL), static_cast<long>(wait_ns % 1000000000LL)};
    const int r = ppoll(&pfd, 1, &ts, nullptr);
    if (r > 0 && (pfd.revents & POLLIN)) {
      const ssize_t n = read(io.fd, buf, sizeof buf);
      if (n > 0) device.receive(buf, static_cast<size_t>(n), dev_us(mono_ns()));
    }
  }

  const mrctl_fw::DeviceCounters& c = device.counters();
  const mrctl_fw::Receiver& rx = device.receiver();
  printf("mrctl_fw_host summary ticks=%u late_ticks=%llu setpoints=%u samples_sent=%u errors_sent=%u "
         "watchdog_trips=%u sync_overflows=%u estops=%u crc_errors=%u header_errors=%u bytes_discarded=%u "
         "tx_dropped=%u applied_A=%g output_enabled=%d\n",
         c.ticks, static_cast<unsigned long long>(late_ticks), c.setpoints, c.samples_sent, c.errors_sent,
         c.watchdog_trips, c.sync_overflows, c.estops, rx.crc_errors, rx.header_errors, rx.bytes_discarded, io.tx_dropped,
         static_cast<double>(device.applied_A()), device.output_enabled() ? 1 : 0);
  fflush(stdout);
  char target[512];
  const ssize_t m = readlink(args.link.c_str(), target, sizeof target - 1);
  if (m > 0 && static_cast<size_t>(m) == tty.size() && tty.compare(0, tty.size(), target, m) == 0)
    unlink(args.link.c_str());
  close(io.fd);
  close(slave);
  return 0;
}
