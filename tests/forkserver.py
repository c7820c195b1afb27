"""A fork server for the doc-snippet tests: ``hsi-torch`` and ``python -c`` without a fresh import.

Every ``hsi-torch`` call of a snippet and every Python snippet used to start a new interpreter that
imported torch, NumPy, SciPy, OpenCV and the package again (about 3 CPU-seconds each, some 60
times per suite). Here one server process imports them once (:data:`PRELOAD`, import only: no
kernel runs, no thread pool starts before a fork) and forks a child per request; the child takes
the caller's standard streams (passed over a Unix socket), working folder, environment and
arguments, and runs the request as a fresh interpreter would:

* ``client SOCKET cli ARGS...``: ``python -m hsi_torch ARGS...`` (``runpy``, as ``-m`` does);
* ``client SOCKET code CODE``: ``python -c CODE`` (a new ``__main__`` module).

The child ends as an interpreter ends (``atexit`` handlers, non-daemon threads joined, streams
flushed); the server reaps it and sends its exit status (``128 + N`` for signal N, as a shell
reports it) to the client, which exits with it. What differs from a fresh interpreter: modules in
:data:`PRELOAD` read their import-time settings from the environment the server was started with
(the snippets' environment, which no snippet changes).

The client imports the standard library only and runs with ``python -S -E`` (no site-packages:
about 20 ms). Test helper only; the package never uses it.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import sys

#: imported by the server before it forks (the package's heavy dependencies and its entry points)
PRELOAD = (
    "torch",
    "numpy",
    "scipy.linalg",
    "cv2",
    "hsi_torch.cli",
    "hsi_torch.recon.pipeline",
    "hsi_torch.calibrate.pipeline",
    "hsi_torch.simulate.capture_sets",
)
_LEN = struct.Struct("!Q")


def _recv_exact(conn: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = conn.recv(n - len(buf))
        if not chunk:
            raise EOFError("the connection closed mid-message")
        buf += chunk
    return buf


# ------------------------------------------------------------------------------------- client
def client(sock_path: str, kind: str, args: list[str]) -> int:
    """Send ``kind`` (``cli`` or ``code``) and ``args`` with this process's streams, working
    folder and environment; return the child's exit status."""
    msg = json.dumps({"kind": kind, "args": args, "cwd": os.getcwd(),
                      "env": dict(os.environ)}).encode()  # fmt: skip
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
        conn.connect(sock_path)
        socket.send_fds(conn, [_LEN.pack(len(msg)) + msg], [0, 1, 2])
        raw = b""
        while chunk := conn.recv(64):
            raw += chunk
    if len(raw) != 4:
        print(f"forkserver: no exit status for {kind} {args[:3]}", file=sys.stderr)
        return 70
    return struct.unpack("!i", raw)[0]


# ------------------------------------------------------------------------------------- server
def _request(conn: socket.socket) -> dict:
    """Read one request, install its streams (fds 0, 1, 2), folder and environment."""
    head, fds, _, _ = socket.recv_fds(conn, _LEN.size, 3)
    if len(head) < _LEN.size:
        head += _recv_exact(conn, _LEN.size - len(head))
    req = json.loads(_recv_exact(conn, _LEN.unpack(head)[0]))
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    os.chdir(req["cwd"])
    os.environ.clear()
    os.environ.update(req["env"])
    return req


def _run_child(req: dict) -> None:
    """Run the request in this (forked) process as ``python -m hsi_torch`` / ``python -c``
    would; returns or raises ``SystemExit`` as they end."""
    import runpy
    import types

    if req["kind"] == "cli":
        sys.argv = ["hsi_torch", *req["args"]]
        sys.path[0] = os.getcwd()
        runpy.run_module("hsi_torch", run_name="__main__", alter_sys=True)
    else:
        sys.argv = ["-c"]
        sys.path[0] = ""
        main = types.ModuleType("__main__")
        sys.modules["__main__"] = main
        exec(compile(req["args"][0], "<string>", "exec"), main.__dict__)


def serve(sock_path: str) -> dict | None:
    """Preload, listen on ``sock_path``, print ``ready``; fork a child per connection. Returns
    the request in a child (the caller runs it); the server itself runs until it is killed."""
    import importlib
    import selectors

    for name in PRELOAD:
        importlib.import_module(name)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(sock_path)
    listener.listen(16)
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    sel = selectors.DefaultSelector()
    sel.register(listener, selectors.EVENT_READ)
    sel.register(wake_r, selectors.EVENT_READ)
    waiting: dict[int, socket.socket] = {}  # child pid -> its client's connection
    print("ready", flush=True)
    while True:
        for key, _ in sel.select():
            if key.fileobj is listener:
                conn, _ = listener.accept()
                sys.stdout.flush()
                sys.stderr.flush()
                pid = os.fork()
                if pid == 0:  # the child: drop the server's state, take the request
                    signal.set_wakeup_fd(-1)
                    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                    sel.close()
                    listener.close()
                    os.close(wake_r)
                    os.close(wake_w)
                    for other in waiting.values():
                        other.close()
                    try:
                        return _request(conn)
                    finally:
                        conn.close()
                waiting[pid] = conn
                continue
            os.read(wake_r, 4096)
            while waiting:
                pid, status = os.waitpid(-1, os.WNOHANG)
                if pid == 0:
                    break
                code = os.waitstatus_to_exitcode(status)
                conn = waiting.pop(pid)
                try:
                    conn.sendall(struct.pack("!i", code if code >= 0 else 128 - code))
                except OSError:
                    pass  # the client is gone (killed at its timeout)
                conn.close()


if __name__ == "__main__":
    if sys.argv[1] == "client":
        raise SystemExit(client(sys.argv[2], sys.argv[3], sys.argv[4:]))
    request = serve(sys.argv[2])
    if request is not None:
        _run_child(request)
