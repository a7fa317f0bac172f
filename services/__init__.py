"""services: everything that runs dosppm. The `dosppm` command (`cli/`), the
server and tracer roles (`server/`, `tracer/`: pure state machines behind
I/O shells), the wire protocol (`wire.py`) and its transport
(`transport.py`, the only ZeroMQ module), and the evaluation harnesses
(`evaluation/`). They drive `dosppm_core`'s kernels and job records and
know nothing of BSDFs; see docs/architecture.md."""
