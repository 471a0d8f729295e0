"""Where a campaign's tasks run (:mod:`opnav.studies.campaign`): local processes, or a dask scheduler.

Both offer ``free()`` (the workers that can take a task now), ``send(worker, function, *arguments)``
(returns a ticket), ``wait()`` ((ticket, result) of the tasks that have finished, once one has) and
``close()``.

``LocalWorkers(count)`` starts ``count`` processes, forked from this one when that is safe
(:func:`fork_safe`; else spawned), each reading ``(function, arguments)`` from its own pipe, running
it and sending back the result or the exception it raised. Unlike a process pool, the caller
chooses the worker: a campaign sends the posterior bound to the worker that still holds the first
seed's simulation in its memory (:func:`keep`, :func:`kept`), and keeps each worker to one task at
a time so that the next task goes to whichever worker is free first.

No thread is started here: the workers are all forked before any task runs, from a process with
one thread. A worker that ends without an answer (killed, out of memory) is one
:class:`~opnav.errors.OpnavError` line.

``SchedulerWorkers(address)`` sends the tasks to an existing dask.distributed scheduler (``dask
scheduler`` and ``dask worker ADDRESS`` on machines sharing the output folder), which places them
itself: every task can be sent at once (``free()`` is always one more), and the earlier sent runs first.
"""

from __future__ import annotations

import sys
from multiprocessing.connection import wait

from ..errors import InputError, OpnavError

#: What a worker process keeps between its tasks (:func:`keep`), by key.
_KEPT: dict[str, object] = {}


def keep(key: str, value) -> None:
    """Keep ``value`` in this process under ``key`` for a later task sent to the same worker (:func:`kept`)."""
    _KEPT[key] = value


def kept(key: str):
    """The value kept under ``key`` in this process (:func:`keep`), forgotten here; None when there is none."""
    return _KEPT.pop(key, None)


def fork_safe() -> bool:
    """Whether worker processes may be forked from this one: numba has not started its thread pool here
    (a forked child would take the pool for started, without its threads, and its parallel kernels
    would wait for them forever). A campaign command has not run a kernel when it starts its workers."""
    parallel = sys.modules.get("numba.np.ufunc.parallel")
    return parallel is None or getattr(parallel, "_is_initialized", True) is False


def _serve(connection) -> None:
    """A worker's loop: run each ``(function, arguments)`` received, send ``(True, result)`` or
    ``(False, exception)``; end on None or when the campaign's end of the pipe is closed. Ctrl-C is the
    campaign's to handle (it stops its workers): a worker ignores it."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    while True:
        try:
            message = connection.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        function, arguments = message
        try:
            answer = (True, function(*arguments))
        except Exception as exc:  # noqa: BLE001 - raised again in the campaign's process
            answer = (False, exc)
        try:
            connection.send(answer)
        except Exception as exc:  # noqa: BLE001 - an answer that cannot be pickled: say what it was
            connection.send((False, OpnavError(f"a campaign worker's answer could not be sent back: "
                                               f"{type(exc).__name__}: {exc}")))


class LocalWorkers:
    """``count`` worker processes (module notes), started at once.

    Parameters
    ----------
    count : int
        Number of processes.
    """

    def __init__(self, count: int) -> None:
        import multiprocessing

        fork = fork_safe()
        context = multiprocessing.get_context("fork" if fork else "spawn")
        if fork:
            # what this process holds out of the collector's sight in the workers: a collection there would
            # otherwise write into every inherited object, copying each page of them into every worker
            import gc

            gc.freeze()
        self._processes, self._pipes = [], []
        for _ in range(count):
            ours, theirs = context.Pipe()
            process = context.Process(target=_serve, args=(theirs,), name="opnav-campaign-worker")
            process.start()
            theirs.close()
            self._processes.append(process)
            self._pipes.append(ours)
        if fork:
            gc.unfreeze()
        self.busy: set[int] = set()

    @property
    def count(self) -> int:
        return len(self._processes)

    def free(self) -> list[int]:
        """The workers without a task."""
        return [worker for worker in range(self.count) if worker not in self.busy]

    def send(self, worker: int, function, *arguments) -> int:
        """Run ``function(*arguments)`` on worker ``worker`` (which must be free); its result comes from
        :meth:`wait` with the ticket returned, the worker's index. ``function`` is sent by name (a
        module-level function)."""
        if worker in self.busy:
            raise RuntimeError(f"worker {worker} is busy")
        self.busy.add(worker)
        self._pipes[worker].send((function, arguments))
        return worker

    def wait(self) -> list[tuple[int, object]]:
        """(worker, result) of each task that has finished, once at least one has; a task's exception is
        raised here. OpnavError when a busy worker ended without an answer."""
        if not self.busy:
            raise RuntimeError("no task is running")
        ready = wait([self._pipes[w] for w in sorted(self.busy)])
        out = []
        for worker in sorted(self.busy):
            pipe = self._pipes[worker]
            if pipe not in ready:
                continue
            try:
                ok, value = pipe.recv()
            except (EOFError, OSError):
                raise OpnavError("a campaign worker process ended abruptly (killed, or out of memory); the runs it "
                                 "finished are kept: run the same command again to resume") from None
            self.busy.discard(worker)
            if not ok:
                raise value
            out.append((worker, value))
        return out

    def close(self, cancel: bool = False) -> None:
        """Let the workers end: each ends after its task (or at once when free); with ``cancel`` they are
        stopped without waiting for their tasks."""
        for worker, (process, pipe) in enumerate(zip(self._processes, self._pipes)):
            if cancel and worker in self.busy and process.is_alive():
                process.terminate()
            try:
                pipe.send(None)
            except (OSError, ValueError):
                pass
            pipe.close()
        if cancel:
            for process in self._processes:
                process.join(timeout=5.0)
        self._processes, self._pipes, self.busy = [], [], set()


#: Seconds a campaign waits for a ``--scheduler`` to answer.
SCHEDULER_TIMEOUT_S = 20.0


def check_scheduler_address(address: str) -> str:
    """``address`` as dask takes it (``tcp://HOST:PORT``; ``HOST:PORT`` gets ``tcp://``), or InputError
    saying what is accepted."""
    text = address.strip()
    if "://" not in text:
        text = f"tcp://{text}"
    protocol, _, rest = text.partition("://")
    host, colon, port = rest.rpartition(":")
    if protocol not in ("tcp", "tls") or not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"--scheduler {address!r}: expected HOST:PORT or tcp://HOST:PORT with a port in "
                         "1-65535 (the address `dask scheduler` prints)")
    return text


class SchedulerWorkers:
    """The workers of the dask scheduler at ``address`` (module notes), which must answer within
    :data:`SCHEDULER_TIMEOUT_S` (else InputError naming the address)."""

    def __init__(self, address: str) -> None:
        from dask.distributed import Client

        checked = check_scheduler_address(address)  # outside the try: InputError is a ValueError
        try:
            self.client = Client(checked, timeout=SCHEDULER_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"--scheduler {address}: no dask scheduler answered there within "
                             f"{SCHEDULER_TIMEOUT_S:g} s ({type(exc).__name__}); start one with `dask scheduler` "
                             "and give the address it prints") from None
        self.order = 0
        self.futures: set = set()

    def free(self) -> list[None]:
        """One more task can always be sent (the scheduler places it)."""
        return [None]

    def send(self, worker: None, function, *arguments):
        """Send ``function(*arguments)`` to the scheduler; returns its future (the ticket)."""
        self.order += 1  # dask runs higher priorities first: the order of sending
        future = self.client.submit(function, *arguments, pure=False, priority=-self.order)
        self.futures.add(future)
        return future

    def wait(self) -> list[tuple[object, object]]:
        """(future, result) of each task that has finished, once at least one has."""
        from dask.distributed import wait

        done, _ = wait(list(self.futures), return_when="FIRST_COMPLETED")
        self.futures -= set(done)
        return [(future, future.result()) for future in done]

    def close(self, cancel: bool = False) -> None:
        """Close the client (its tasks still running go on without it)."""
        if self.client is not None:
            self.client.close()
            self.client = None
