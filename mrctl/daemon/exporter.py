"""``mrctl exporter``: a Prometheus HTTP endpoint outside the control process.

Each scrape asks the daemon's status socket once (:func:`mrctl.daemon.status.query_status`,
a 1 s timeout) and serves :func:`mrctl.daemon.prometheus.families` of the
reply through ``prometheus_client`` (``pip install 'mrctl[metrics]'``). The
control process is never imported into this one and does no work for a
scrape beyond answering the status request on its status thread; a scrape
while no daemon runs gets ``mrctl_up 0``. Run it as its own service (a user
in the ``mrctl`` group may connect to the socket): docs/observe.md.
"""

from __future__ import annotations

from typing import Any, Iterator

from mrctl.daemon.prometheus import families
from mrctl.daemon.status import StatusError, query_status
from mrctl.errors import BadInput, DependencyMissing


def _client() -> Any:
    try:
        import prometheus_client
        import prometheus_client.core
    except ImportError:
        raise DependencyMissing("mrctl exporter needs prometheus-client: pip install 'mrctl[metrics]'") from None
    return prometheus_client


class StatusCollector:
    """A ``prometheus_client`` collector: one status query per scrape."""

    def __init__(self, socket_path: str, damper: str | None = None, timeout_s: float = 1.0) -> None:
        self.socket_path = socket_path
        self.damper = damper
        self.timeout_s = timeout_s

    def collect(self) -> Iterator[Any]:
        from prometheus_client.core import Metric

        try:
            st: dict[str, Any] | None = query_status(self.socket_path, self.timeout_s)
        except StatusError:
            st = None
        for fam in families(st, self.damper):
            # a counter family is named without _total; its samples keep it
            name = fam.name.removesuffix("_total") if fam.type == "counter" else fam.name
            m = Metric(name, fam.help, fam.type)
            for name, labels, value in fam.samples:
                m.add_sample(name, labels, value)
            yield m

    def describe(self) -> list[Any]:
        return []  # the families depend on what the daemon answers


def parse_listen(text: str) -> tuple[str, int]:
    """``:9877``, ``HOST:PORT`` or ``[::1]:9877`` → (address, port); BadInput otherwise."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise BadInput(f"--listen {text!r}: use [HOST]:PORT, e.g. :9877 or 127.0.0.1:9877")
    host = host.strip("[]") or "0.0.0.0"
    return host, int(port)


def start(listen: str, socket_path: str, damper: str | None = None) -> tuple[Any, Any]:
    """Start the HTTP endpoint in a thread; (server, thread) from
    ``prometheus_client.start_http_server`` (``server.server_port`` is the port)."""
    pc = _client()
    addr, port = parse_listen(listen)
    registry = pc.CollectorRegistry(auto_describe=False)
    registry.register(StatusCollector(socket_path, damper))
    try:
        return pc.start_http_server(port, addr=addr, registry=registry)
    except OSError as exc:
        raise BadInput(f"--listen {listen}: cannot listen: {exc.strerror or exc}") from None
