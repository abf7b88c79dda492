"""D5: concurrent status scrapes must not make the daemon's interpreter
work per query: the snapshot is rebuilt at most every REPLY_MAX_AGE_S and
replies are rate-limited, so eight scrapers cost what one does."""

from __future__ import annotations

import threading
import time

from mrctl.daemon import status
from mrctl.daemon.status import StatusServer, query_status


def test_eight_scrapers_share_one_snapshot_per_interval(tmp_path):
    built = [0]

    def snapshot():
        built[0] += 1
        return {"ticks": built[0], "timing": {"samples": 5000}}

    srv = StatusServer(str(tmp_path / "st.sock"), snapshot)
    srv.start()
    answers: list[int] = []
    stop = threading.Event()

    def scrape():
        while not stop.is_set():
            try:
                answers.append(query_status(srv.path, 2.0)["ticks"])
            except OSError:
                pass

    threads = [threading.Thread(target=scrape, daemon=True) for _ in range(8)]
    t0 = time.monotonic()
    for t in threads:
        t.start()
    time.sleep(1.0)
    stop.set()
    for t in threads:
        t.join(5.0)
    elapsed = time.monotonic() - t0
    srv.close()
    assert len(answers) >= 8  # everyone is answered ...
    assert len(answers) <= status.MAX_REPLIES_PER_S * elapsed + 8  # ... at a bounded rate ...
    assert built[0] <= elapsed / status.REPLY_MAX_AGE_S + 2, built[0]  # ... from few snapshots
    assert srv.replies_built == built[0]


def test_a_snapshot_that_raises_does_not_end_the_status_thread(tmp_path):
    calls = [0]

    def snapshot():
        calls[0] += 1
        if calls[0] == 1:
            raise RuntimeError("boom")
        return {"ok": True}

    srv = StatusServer(str(tmp_path / "st.sock"), snapshot)
    srv.start()
    try:
        try:
            query_status(srv.path, 2.0)
        except OSError:
            pass
        time.sleep(status.REPLY_MAX_AGE_S)
        assert query_status(srv.path, 2.0) == {"ok": True}
    finally:
        srv.close()
