"""services: the server and tracer roles, the wire protocol and the
transport (ZeroMQ). They drive `dosppm_core`'s kernels and job records and
know nothing of BSDFs. Empty until the distributed render service lands."""
