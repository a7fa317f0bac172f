"""What a server is told to do, as one object: the flags of `dosppm
server` and `dosppm render` that are not render settings (those are
`RenderSettings`, shared with the library) nor collaborators (the store,
the reporter, the ZeroMQ context).

`ServerProcess` reads the I/O ones (where to bind, write, checkpoint);
`ServerState` the scheduling ones. Both take the whole object, so a new
flag is one field here and one read where it is used.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from dosppm_core.chunks.pacing import FIRST_QUEUE_RAYS
from services import config
from services.server.epochs import MOST_MERGED


@dataclass
class Limits:
    seconds: float | None = None
    photons: float | None = None
    iterations: int | None = None

    def reached(self, seconds: float, photons: int, iterations: int) -> bool:
        return ((self.seconds is not None and seconds >= self.seconds)
                or (self.photons is not None and photons >= self.photons)
                or (self.iterations is not None and iterations >= self.iterations))


@dataclass
class ServerOptions:
    # Where it listens and what it writes.
    bind: str = "tcp://127.0.0.1:5555"
    http: tuple[str, int] | None = ("127.0.0.1", 8080)
    out: str = "out.exr"
    exposure: float = 0.0
    limits: Limits = field(default_factory=lambda: Limits(seconds=config.SECONDS))
    snapshot_interval_s: float = 60.0
    drain_timeout_s: float = 60.0
    threads: int = 2                            # the statistics' kernels
    checkpoint_dir: str | None = None
    checkpoint_interval_s: float = 60.0
    ledger: str | None = None                   # a file recording every update applied (services/ledger.py)
    curve_secret: str | None = None
    curve_clients: str | None = None
    # Scheduling (ServerState).
    min_photon_jobs: int = 1000
    queue_target_rays: int = FIRST_QUEUE_RAYS
    # The render starts once `min_tracers` have registered or, with one,
    # `min_tracers_timeout_s` after the first tick (None: never).
    min_tracers: int = 1
    min_tracers_timeout_s: float | None = None
    tracer_timeout_s: float = 10.0
    # False: two of the paper's optimisations off (Figure 15).
    concurrent: bool = True
    client_batching: bool = True
    held_bytes: float | None = None             # --queue-memory (`HeldDeposits`)
    # "server" (the paper's: deposits sent, held, gathered here) or
    # "tracers" (by epochs: services/server/epoch_state.py).
    gather_at: str = "server"
    # One eye iteration in how many installs its hit points (the rest count
    # their emission only): None, one set per statistics update
    # (`dosppm_core.sppm.iteration.hit_point_stride`) gathering at the tracers, 1 at the server.
    hit_point_stride: int | None = None
    # Gathering at the tracers, epochs one gather may merge into one
    # statistics batch while the round trips hold the render (1: never).
    batch_growth: int = MOST_MERGED
