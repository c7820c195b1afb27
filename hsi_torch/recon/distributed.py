"""The Dask side of a distributed batch run: connecting to a cluster, handing tasks to workers
(the user's side, threads and security: ``docs/cluster.md``).

:func:`connect` gives a ``distributed.Client`` for ``--scheduler local:N`` (a ``LocalCluster`` of
N worker processes on the loopback interface, one task thread each, ``cores // N`` torch and
numba threads a frame unless ``threads_per_worker`` says otherwise), ``--scheduler
tcp://host:8786`` or ``tls://`` (a running scheduler; :func:`make_security` for TLS, a plain
``tcp://`` address not on this machine is warned about: a scheduler can run any code here) or
``--scheduler-file FILE``. :class:`DaskExecutor` runs the tasks of
:func:`hsi_torch.recon.batch.driver.drive` on its workers: twice the cluster's task threads in
flight (at least 4, re-read as workers come and go), results taken as they complete, the
not-yet-started ones cancelled on Ctrl-C. Needs ``pip install 'hsi-torch[cluster]'``, imported
only here.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

__all__ = ["connect", "parse_scheduler", "make_security", "DaskExecutor", "in_dask_worker"]

_HINT = "pip install 'hsi-torch[cluster]'"
_ADDRESS = re.compile(r"^(tcp|tls|ucx|inproc|ws|wss)://\S+$")


def _distributed() -> Any:
    try:
        import distributed  # lazy: optional dependency (the cluster extra)
    except ModuleNotFoundError:
        raise ModuleNotFoundError(
            f"a distributed run needs the optional package 'distributed' (Dask): {_HINT}",
            name="distributed",
        ) from None
    return distributed


_TRIM_KEY = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"


def _dask() -> Any:
    import dask  # lazy: optional dependency (the cluster extra)

    return dask


def _pre_spawn_keys() -> list[str]:
    return [*_dask().config.get("distributed.nanny.pre-spawn-environ", {}), "PYTHONHASHSEED"]


def _restore_environ(saved: dict[str, str | None]) -> None:
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


def in_dask_worker() -> Any | None:
    """The Dask worker running this code, or ``None`` (Dask is never imported here: only a
    process in which it is already loaded can be a worker)."""
    mod = sys.modules.get("distributed")
    if mod is None:
        return None
    try:
        return mod.get_worker()
    except ValueError:  # not in a worker
        return None


def parse_scheduler(spec: str) -> tuple[str, Any]:
    """``"local:N"`` → ``("local", N)``; ``"tcp://host:port"`` (or ``tls://``, ...) →
    ``("address", spec)``.

    Raises:
        ValueError: anything else (the message shows the accepted forms).
    """
    text = str(spec).strip()
    m = re.fullmatch(r"local:(\d+)", text)
    if m:
        n = int(m.group(1))
        if n < 1:
            raise ValueError(f"--scheduler {text!r}: local:N needs N >= 1 worker processes")
        return "local", n
    if _ADDRESS.match(text):
        return "address", text
    raise ValueError(
        f"--scheduler {text!r}: expected local:N (N worker processes on this machine) or a "
        "scheduler address such as tcp://host:8786 (or use --scheduler-file FILE)"
    )


def make_security(
    ca_file: str | os.PathLike | None = None,
    cert: str | os.PathLike | None = None,
    key: str | os.PathLike | None = None,
) -> Any | None:
    """A ``distributed.security.Security`` for a ``tls://`` scheduler: the certificate authority
    that signed the cluster's certificates (``ca_file``) and this client's certificate and
    private key (``cert``, ``key``; one PEM file holding both may be given as ``cert`` alone).
    Encryption is required. ``None`` when no file is given.

    Raises:
        ValueError: a CA without a certificate or the other way round.
        FileNotFoundError: a file that does not exist (named).
    """
    if ca_file is None and cert is None and key is None:
        return None
    if ca_file is None or cert is None:
        raise ValueError("TLS needs --tls-ca-file (the cluster's certificate authority) and "
                         "--tls-cert (this client's certificate; --tls-key for its key if it is "
                         "not in the same file)")  # fmt: skip
    for what, f in (("--tls-ca-file", ca_file), ("--tls-cert", cert), ("--tls-key", key)):
        if f is not None and not Path(f).is_file():
            raise FileNotFoundError(f"{what} {f} not found")
    Security = _distributed().security.Security  # noqa: N806 - a class
    return Security(
        tls_ca_file=str(ca_file), tls_client_cert=str(cert),
        tls_client_key=None if key is None else str(key), require_encryption=True,
    )  # fmt: skip


#: Schemes of Dask addresses reached without encryption or authentication.
_PLAIN_SCHEMES = ("tcp://", "ws://", "ucx://")


def _warn_plain(address: str) -> None:
    """A warning for a plaintext (``tcp://``, ``ws://``, ``ucx://``) scheduler not on this
    machine (no encryption, no authentication)."""
    if "://" not in address:
        return
    host = address.split("://", 1)[1].split("/", 1)[0].rsplit(":", 1)[0].strip("[]")
    if address.startswith(_PLAIN_SCHEMES) and host not in ("127.0.0.1", "localhost", "::1"):
        print(f"hsi-torch: warning: the scheduler {address} is reached without encryption or "
              "authentication: whoever can reach it can run code in this process and on the "
              "workers; use tls:// with --tls-ca-file/--tls-cert/--tls-key on networks you do "
              "not fully trust (docs/cluster.md, Security)", file=sys.stderr)


def _file_address(path: Path) -> str:
    """The ``address`` a scheduler file names (``""`` when it cannot be read: the client then
    reports the file)."""
    from hsi_torch.io.atomic import read_own_json  # lazy: atomic imports numpy

    doc = read_own_json(path, 1 << 20, follow=True)
    address = doc.get("address") if isinstance(doc, dict) else None
    return address if isinstance(address, str) else ""


@contextlib.contextmanager
def connect(
    scheduler: str | None = None,
    scheduler_file: str | os.PathLike | None = None,
    *,
    threads_per_worker: int | None = None,
    timeout_s: float = 30.0,
    security: Any | None = None,
) -> Iterator[tuple[Any, int | None]]:
    """A ``distributed.Client`` for the run, and the torch/numba threads per frame.

    Args:
        scheduler: ``local:N`` or a scheduler address (see :func:`parse_scheduler`).
        scheduler_file: the JSON file a scheduler wrote (``dask scheduler --scheduler-file``).
        threads_per_worker: torch/numba threads per frame (default: ``cores // N`` for
            ``local:N``; ``None`` otherwise: each worker's Dask thread count).
        timeout_s: how long to wait for the scheduler.
        security: a ``distributed.security.Security`` (:func:`make_security`) for a
            ``tls://`` scheduler; required for one. ``local:N`` clusters listen on 127.0.0.1.

    Yields:
        ``(client, threads)``; on exit the client is closed and a ``local:N`` cluster shut down.

    Raises:
        ValueError: bad ``scheduler``, both or neither given, ``threads_per_worker < 1``.
        FileNotFoundError: the scheduler file does not exist.
        OSError: the scheduler cannot be reached (the message names it).
    """
    if bool(scheduler) == bool(scheduler_file):
        raise ValueError("give one of --scheduler and --scheduler-file")
    if threads_per_worker is not None and threads_per_worker < 1:
        raise ValueError(f"--threads-per-worker must be >= 1, got {threads_per_worker}")
    kind, value = parse_scheduler(scheduler) if scheduler else ("file", Path(scheduler_file))
    if kind == "file" and not Path(value).is_file():
        raise FileNotFoundError(f"scheduler file not found: {value}")
    if kind == "address" and str(value).startswith("tls://") and security is None:
        raise ValueError(f"--scheduler {value}: a tls:// scheduler needs certificates: "
                         "--tls-ca-file, --tls-cert (and --tls-key)")  # fmt: skip
    if kind == "local" and security is not None:
        raise ValueError("--tls-* options are for a running tls:// scheduler; local:N listens on "
                         "127.0.0.1 only")  # fmt: skip
    if kind == "address" and security is not None and not str(value).startswith("tls://"):
        raise ValueError(f"--scheduler {value}: TLS certificates were given; the address must "
                         "start with tls://")  # fmt: skip
    distributed = _distributed()
    cluster = None
    threads = threads_per_worker
    with contextlib.ExitStack() as stack:
        if kind == "local":
            # a nanny sets its pre-spawn variables (OMP_NUM_THREADS=1, ...) in *this* process's
            # environment before it starts a worker: put them back afterwards, so that later
            # child processes of the caller are not affected
            saved = {k: os.environ.get(k) for k in _pre_spawn_keys()}
            stack.callback(_restore_environ, saved)
            # the nanny's default MALLOC_TRIM_THRESHOLD_ makes glibc hand every large temporary
            # back and map it afresh: a full-size frame took 1.5 s instead of 0.8 s in a
            # worker; leave glibc's own setting
            with _dask().config.set({_TRIM_KEY: None}):
                cluster = distributed.LocalCluster(
                    n_workers=value, threads_per_worker=1, processes=True,
                    host="127.0.0.1", dashboard_address=None, silence_logs=logging.ERROR,
                )  # fmt: skip
            _restore_environ(saved)
            stack.callback(cluster.close)
            client = distributed.Client(cluster)
            if threads is None:
                threads = max(1, (os.cpu_count() or 1) // value)
        else:
            where = f"scheduler {value}" if kind == "address" else f"scheduler file {value}"
            if kind == "address" and security is None:
                _warn_plain(str(value))
            elif kind == "file" and security is None:
                _warn_plain(_file_address(Path(value)))
            sec = {} if security is None else {"security": security}
            try:
                client = (distributed.Client(value, timeout=timeout_s, **sec) if kind == "address"
                          else distributed.Client(scheduler_file=str(value), timeout=timeout_s,
                                                  **sec))  # fmt: skip
            except (OSError, TimeoutError) as exc:
                raise OSError(f"cannot connect to the {where}: {exc}") from None
        stack.callback(client.close)
        yield client, threads


class DaskExecutor:
    """Runs the tasks of :func:`hsi_torch.recon.batch.driver.drive` on a cluster's workers (see the
    module docstring). :meth:`share` scatters data (the bundle's bytes) to every worker once; the
    copies are kept while the executor lives, and workers that join later fetch one from
    another."""

    def __init__(self, client: Any) -> None:
        distributed = _distributed()
        self.client = client
        self._ac = distributed.as_completed()
        self._shared: list[Any] = []
        self._window = 4
        self._window_at = float("-inf")

    def share(self, data: bytes) -> Any:
        fut = self.client.scatter(data, broadcast=True, hash=False)
        self._shared.append(fut)
        return fut

    def window(self) -> int:
        """Tasks in flight: twice the cluster's task threads (at least 4), re-read every 2 s."""
        now = time.monotonic()
        if now - self._window_at > 2.0:
            with contextlib.suppress(Exception):  # keep the last value if the scheduler is busy
                self._window = max(4, 2 * sum(self.client.nthreads().values()))
            self._window_at = now
        return self._window

    def submit(self, fn: Callable[..., dict[str, Any]], *args: Any, name: str) -> Any:
        key = f"hsi-reconstruct-{name}-{uuid.uuid4().hex[:8]}"
        fut = self.client.submit(fn, *args, key=key, pure=False)
        self._ac.add(fut)
        return fut

    def wait_one(self) -> tuple[Any, dict[str, Any] | None, BaseException | None]:
        fut = next(self._ac)
        try:
            return fut, fut.result(), None
        except Exception as exc:  # noqa: BLE001 - KilledWorker, CancelledError, ...
            return fut, None, exc

    def cancel(self, tokens: Iterable[Any]) -> None:
        futs = list(tokens)
        if futs:
            with contextlib.suppress(Exception):
                self.client.cancel(futs, force=True)

