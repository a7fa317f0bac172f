"""The records the server's state keeps: a tracer, a job, an eye
iteration in flight, and the statistics updates it hands to the shell."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from dosppm_core.jobs import HitPoints
from dosppm_core.sppm.iteration import EyePass
from services.credit import Account


@dataclass
class TracerInfo:
    id: str
    index: int
    endpoint: str
    cores: int
    memory_bytes: int
    store_key: str | None
    last_seen_s: float
    public_key: str | None = None   # its CURVE key, handed to its peers
    session: int = 0                # counts its welcomes; heartbeats echo the one it got
    welcomed_s: float = 0.0
    status_s: float = -1e30         # when its last heartbeat came
    jobs_sent: int = 0              # job messages sent since the welcome...
    unacked: deque = field(default_factory=deque)   # ...and when, for those not yet acknowledged
    queued: int = 0                 # rays waiting at the tracer, as last reported
    queue_target: int = 0           # rays it asks to have queued (0: the server's queue allowance)
    sent_since_report: int = 0      # rays sent to it since
    status: dict = field(default_factory=dict)
    rays_sent: int = 0
    results: int = 0

    @property
    def load_estimate(self) -> int:
        return self.queued + self.sent_since_report


@dataclass
class Job:
    kind: str                        # "photon" or "eye"
    paths: int                       # N_j, counted as emitted when complete
    eye_iteration: int | None = None
    credit: Account = field(default_factory=Account)   # returned so far (services/credit.py)
    sent: bool = False               # all its paths have left the server
    progress_s: float = 0.0          # when a result last touched it (the watchdog's clock)
    # The photon job whose random streams this one traces: itself, or the
    # job it re-emits after a tracer failure (the same photons, a new id).
    rng_key: int | None = None
    cull_box: np.ndarray | None = None    # a photon job's, as sent (§4.3)
    sent_s: float = 0.0              # when it left the server (its latency, `latency_estimate_s`)


@dataclass
class EyeIteration:
    index: int
    open_jobs: int
    results: EyePass = field(default_factory=EyePass)


@dataclass
class Update:
    """One statistics step for the shell to run, in order: install the hit
    points of a complete eye iteration, or apply a batch of photons."""
    kind: str                        # "hits", "light", "photons", "checkpoint" or "snapshot" (the image)
    hits: HitPoints | None = None
    emitted_light: tuple | None = None
    deposits: list | None = None     # "photons": the batch, as the parts it arrived in
    photons_emitted: int = 0
    directory: str | None = None     # "checkpoint": where, and what besides the statistics
    meta: dict | None = None
    # What was applied, for the ledger (services/ledger.py): the eye
    # iteration of "hits"; the committed jobs of "photons" as (rng keys,
    # paths, cull boxes (n, 2, 3)).
    eye_iteration: int | None = None
    jobs: tuple | None = None
    # Gather at the tracers (services/server/epochs.py): "gather" asks the
    # statistics for the request of the epoch's next round after `stage`
    # ("start", "count" or "pilot", with that round's summed `sums`), which
    # it leaves in `request`; "epoch" applies the summed sums. "hits" leaves
    # the installed hit points, in the statistics' order, in `installed`.
    epoch: object = None
    stage: str | None = None
    sums: dict | None = None
    request: dict | None = None
    installed: object = None
    # "light": a round of eye light collected from the tracers
    # (services/server/eye_light.py), per pixel, and how many eye
    # iterations it is the light of.
    light: object = None
    light_iterations: int = 0
