#!/opt/dosppm/bin/python
"""Health probe of a tracer container: healthy while a `dosppm worker`
process runs and holds an established TCP connection to the server's port
(the tracer's ZeroMQ DEALER to the server). The server's endpoint is read
from DOSPPM_SERVER (default tcp://127.0.0.1:5555), as the tracer reads it.
Exit 0 healthy, 1 not (with one line saying why)."""
import os
import sys


def tracer_running() -> bool:
    me = str(os.getpid())
    for pid in os.listdir("/proc"):
        if not pid.isdigit() or pid == me:
            continue
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
        except OSError:
            continue
        if any(a.endswith(b"dosppm") for a in argv[:2]) and b"worker" in argv:
            return True
    return False


def connected(port: int) -> bool:
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(table) as f:
                rows = f.read().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            fields = row.split()
            remote, state = fields[2], fields[3]
            if state == "01" and int(remote.rsplit(":", 1)[1], 16) == port:   # 01: ESTABLISHED
                return True
    return False


def main() -> int:
    server = os.environ.get("DOSPPM_SERVER", "tcp://127.0.0.1:5555")
    port = server.rsplit(":", 1)[-1]
    if not tracer_running():
        print("no dosppm worker process")
        return 1
    if not port.isdigit() or not connected(int(port)):
        print(f"tracer not connected to {server}")
        return 1
    print(f"tracer connected to {server}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
