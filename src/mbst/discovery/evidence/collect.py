"""Run the evidence methods beside the structure test (identification tests only).

A failure of one method is recorded in its place and never sinks the discovery.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor

from mbst.core.candidates import LibraryFactory
from mbst.discovery.data import TestResidual
from mbst.discovery.state import DiscoverSettings

log = logging.getLogger(__name__)


def sparse_evidence(id_res: list[TestResidual], library: LibraryFactory) -> dict | None:
    from mbst.discovery.evidence.sindy import residual_regression

    try:
        ev = residual_regression(id_res, library)
    except Exception as exc:  # evidence only: a failure must not sink the discovery
        log.warning("sparse-regression evidence failed: %s: %s", type(exc).__name__, exc)
        return {"error": f"{type(exc).__name__}: {exc}", "ranking": []}
    d = ev.to_dict()
    d["ranking"] = [list(x) for x in ev.ranking]
    return d


def neural_evidence(id_res: list[TestResidual], settings: DiscoverSettings,
                    library: LibraryFactory):
    from mbst.discovery.evidence import neural

    kw = {"seed": settings.identify.seed}
    if settings.neural_iterations is not None:
        kw["iterations"] = settings.neural_iterations
    try:
        model = neural.NeuralResidual(**kw).fit(id_res)
        ev = neural.explain(model, id_res, library)
    except Exception as exc:  # evidence only: a failure must not sink the discovery
        log.warning("neural-residual evidence failed: %s: %s", type(exc).__name__, exc)
        return None, {"error": f"{type(exc).__name__}: {exc}", "ranking": []}
    ev["train_seconds"] = getattr(model, "train_seconds", None)
    return model, ev


def _yield_to_the_refits() -> None:
    """The training process runs at a lower priority: it fills what the refits leave of
    the cores (their Python between simulations, the rounds after them) rather than take
    a third of two cores from them. On the demo the network trained in 95-133 s instead of
    40 s and was still ready before it was needed; the structure rounds took 147-164 s
    instead of 169 s. The work is the same, so a rig where the rounds end first waits as
    long as before."""
    try:
        os.nice(10)
    except (AttributeError, OSError):  # no nice on this platform: an even share
        pass


class NeuralJob:
    """The neural evidence trained beside the structure test, in a process of its own.

    A thread beside the refits held the interpreter lock for torchdiffeq's step loop
    (Python per step): on the demo it trained in 93 s and the structure test took 176 s
    (143 s without the network); in a spawned process, which shares the cores but not the
    lock, 75 s and 165 s. Where the process cannot start or dies (a calling script without the
    ``if __name__ == "__main__":`` guard that spawning needs, memory), the network trains
    in a thread instead and the log says why: the evidence is never lost to the process.
    """

    def __init__(self, id_res: list[TestResidual], settings: DiscoverSettings,
                 library: LibraryFactory) -> None:
        self._args = (id_res, settings, library)
        self._pool: ProcessPoolExecutor | ThreadPoolExecutor
        try:
            self._pool = ProcessPoolExecutor(
                max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                initializer=_yield_to_the_refits)
            self._job: Future = self._pool.submit(neural_evidence, *self._args)
        except Exception as exc:  # no process: the thread keeps the evidence
            log.warning("neural residual: no process of its own (%s: %s), trained in a "
                        "thread", type(exc).__name__, exc)
            self._in_thread()

    def _in_thread(self) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mbst-neural")
        self._job = self._pool.submit(neural_evidence, *self._args)

    def result(self):
        """The trained model and its evidence (``neural_evidence``)."""
        try:
            return self._job.result()
        except Exception as exc:  # the process died: train here rather than lose it
            if isinstance(self._pool, ThreadPoolExecutor):
                raise
            log.warning("neural residual: its process failed (%s: %s), trained in a thread "
                        "(is the calling script guarded by if __name__ == '__main__'?)",
                        type(exc).__name__, exc)
            self.close()
            t0 = time.perf_counter()
            self._in_thread()
            model, ev = self._job.result()
            log.info("neural residual retrained in %.0f s", time.perf_counter() - t0)
            return model, ev
        finally:
            self.close()

    def close(self) -> None:
        """Stop the training if it still runs (discovery failed before it was needed)."""
        # the executor has no public way to end a running task before Python 3.14
        processes = dict(getattr(self._pool, "_processes", None) or {})
        self._pool.shutdown(wait=False, cancel_futures=True)
        for proc in processes.values():
            if proc.is_alive():
                proc.terminate()
