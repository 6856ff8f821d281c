"""Run a grid on a Dask cluster: an embedded ``LocalCluster``, or one given by address.

Each cell is one Dask task (:func:`cell_task`). Before any task runs, every worker gets
:class:`MitsubaWorkerSetup`, which sets the Mitsuba variant and a Dr.Jit thread count such
that, on each host, workers x threads <= the cores available there, with one exception:
a worker gets at least :data:`MIN_DRJIT_THREADS` threads, so a host with fewer than that
many cores per worker is oversubscribed (and a warning says so). A worker runs one cell
at a time even if it has several Dask threads (cells time their renders; two in one
process would share its Dr.Jit thread pool).

Only this process writes the output folder (:class:`~.store.CellStore`); finished cells are
skipped, so running a sweep again computes only what is missing, failed or changed.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import sys
import threading
import time

from distributed import Client, LocalCluster, WorkerPlugin, as_completed, get_worker
from distributed.comm import get_address_host
from tqdm import tqdm

from . import aggregate
from .cells import CellResult, cell_inputs, cell_key, code_version, run_cell, use_variant
from .grid import Cell, Grid
from .store import CellStore

#: Event topic on which a worker announces that a cell started running.
TOPIC = "mitsuba-shsampling-sweep"
_ONE_CELL_AT_A_TIME = threading.Lock()
#: ``dr.set_thread_count(1)`` leaves Dr.Jit without worker threads (the caller counts as one),
#: and then Mitsuba 3.9.1's EXR reader and writer wait forever for a pool task (measured:
#: ``mi.Bitmap(...).write("x.exr")`` hangs). Every report writes EXRs, so 2 is the minimum.
MIN_DRJIT_THREADS = 2


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


class MitsubaWorkerSetup(WorkerPlugin):
    """Sets the Mitsuba variant and the Dr.Jit thread count of a worker process.

    :param variant: Mitsuba variant of every cell.
    :param threads: Dr.Jit threads per worker address; a worker not listed (one that joined
        or restarted later) gets :data:`MIN_DRJIT_THREADS`.
    """

    name = "mitsuba-shsampling-sweep"

    def __init__(self, variant: str, threads: dict[str, int]):
        self.variant = variant
        self.threads = threads

    def setup(self, worker) -> None:
        import drjit as dr

        use_variant(self.variant)
        dr.set_thread_count(self.threads.get(worker.address, MIN_DRJIT_THREADS))


def thread_plan(cores: dict[str, int]) -> dict[str, int]:
    """Dr.Jit threads per worker: the cores of its host shared by the workers on that host
    (at least :data:`MIN_DRJIT_THREADS`).

    :param cores: available cores as each worker (by address) sees them.
    """
    per_host = collections.Counter(get_address_host(address) for address in cores)
    return {address: max(MIN_DRJIT_THREADS, n // per_host[get_address_host(address)])
            for address, n in cores.items()}


def oversubscribed_hosts(cores: dict[str, int], threads: dict[str, int]) -> list[str]:
    """Hosts where the workers' threads add up to more than the host's cores."""
    total: dict[str, int] = collections.Counter()
    host_cores = {}
    for address, n in threads.items():
        host = get_address_host(address)
        total[host] += n
        host_cores[host] = cores[address]
    return sorted(h for h, n in total.items() if n > host_cores[h])


def cell_task(cell: Cell, expected_code: str, cache_dir: str | None) -> CellResult:
    """The Dask task of one cell: checks the worker runs the client's code, then :func:`run_cell`."""
    if code_version() != expected_code:
        return CellResult("failed", error=f"the worker runs other code ({code_version()}) than the "
                          f"sweep ({expected_code}): install the same version on every worker",
                          code_version=code_version())
    with _ONE_CELL_AT_A_TIME:
        get_worker().log_event(TOPIC, {"running": cell.label})
        return run_cell(cell, cache_dir)


@dataclasses.dataclass
class SweepSummary:
    """Which cells a sweep computed, reused from ``out`` and saw fail (labels), and its report."""

    computed: list[str]
    reused: list[str]
    failed: dict[str, str]
    aggregate_json: str
    index_html: str


def _connect(scheduler: str | None, workers: int | None, n_cells: int):
    """(client, cluster or None): an embedded LocalCluster, or a client of ``scheduler``."""
    if scheduler is None:
        n = workers or max(1, min(n_cells, available_cores() // MIN_DRJIT_THREADS))
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=None)
        return Client(cluster), cluster
    client = Client(scheduler)
    client.wait_for_workers(workers or 1)
    return client, None


def run_sweep(grid: Grid, out: str, scheduler: str | None = None, workers: int | None = None,
              cache_dir: str | None = None, progress: bool = True) -> SweepSummary:
    """Compute the grid's missing cells on a cluster, then write the aggregate report.

    :param grid: the parsed grid.
    :param out: output folder (created); see :mod:`.store` for its layout.
    :param scheduler: address of a running Dask scheduler (``tcp://host:port``); None starts
        a ``LocalCluster`` of ``workers`` processes on this machine.
    :param workers: embedded cluster: worker processes (default: one per
        :data:`MIN_DRJIT_THREADS` cores, at most one per cell to compute). With ``scheduler``:
        how many workers to wait for before starting.
    :param cache_dir: reference cache on the workers (None: compare's default there).
    :param progress: show a progress bar (cells done, running, failed).
    """
    store = CellStore(out)
    cells = grid.cells()
    keyed = []
    for cell in cells:
        inputs = cell_inputs(cell)
        keyed.append((cell, inputs, cell_key(inputs)))
    todo = [(c, i, k) for c, i, k in keyed if not store.finished(c, k)]
    reused = [c.label for c, _, k in keyed if store.finished(c, k)]
    computed: list[str] = []
    failed: dict[str, str] = {}

    if todo:
        client, cluster = _connect(scheduler, workers, len(todo))
        try:
            computed, failed = _compute(client, grid.variant, todo, store, cache_dir, len(cells),
                                        len(reused), progress)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()

    entries = [(cell, key, store.record(cell, key), store.report(cell, key)) for cell, _, key in keyed]
    paths = aggregate.write_aggregate(out, grid, entries, code_version())
    return SweepSummary(computed, reused, failed, paths["json"], paths["html"])


def _compute(client: Client, variant: str, todo: list, store: CellStore, cache_dir: str | None,
             total: int, done: int, progress: bool) -> tuple[list[str], dict[str, str]]:
    cores = client.run(available_cores)
    threads = thread_plan(cores)
    for host in oversubscribed_hosts(cores, threads):
        print(f"warning: the workers on {host} use more Dr.Jit threads than it has cores (each needs "
              f"{MIN_DRJIT_THREADS}); timings of concurrent cells slow each other down", file=sys.stderr)
    client.register_plugin(MitsubaWorkerSetup(variant, threads))
    # Start events come from the workers and may arrive after the result itself.
    started: set[str] = set()
    client.subscribe_topic(TOPIC, lambda event: started.add(event[1]["running"]))
    code = code_version()
    futures = {client.submit(cell_task, cell, code, cache_dir, key=f"cell-{key}", pure=False):
               (cell, inputs, key) for cell, inputs, key in todo}
    computed, failed, finished, status = [], {}, set(), ""
    with tqdm(total=total, initial=done, desc="sweep", unit="cell", disable=not progress,
              file=sys.stderr) as bar:
        pending = as_completed(futures)
        while not pending.is_empty():
            batch = pending.next_batch(block=False)
            for future in batch:
                cell, inputs, key = futures[future]
                result = _result(future)
                store.save(cell, key, inputs, result)
                finished.add(cell.label)
                if result.status == "ok":
                    computed.append(cell.label)
                else:
                    failed[cell.label] = result.error
                bar.update(1)
            # Redraw only on change: a bar on a non-terminal stderr prints every redraw as a line.
            if f"running {len(started - finished)}, failed {len(failed)}" != status:
                status = f"running {len(started - finished)}, failed {len(failed)}"
                bar.set_postfix_str(status)
            if not batch:
                time.sleep(0.2)
    client.unsubscribe_topic(TOPIC)
    return computed, failed


def _result(future) -> CellResult:
    """The task's result, or a failed result if the task itself died (worker lost, cancelled)."""
    try:
        return future.result()
    except Exception as err:
        return CellResult("failed", error=f"{type(err).__name__}: {err}")
