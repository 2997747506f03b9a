"""Work in a second process while this one goes on: a call started now, its value collected later.

On a two-core machine the bake has long single-threaded stretches (reading meshes, METIS
ordering, SciPy's Dijkstra, which holds the GIL); a second *process* fills the other core
where a thread could not. The child is a fresh interpreter running this module
(``python -m facepipe.pipeline.background IN OUT``), not a fork, so it is safe beside the threads and
OpenMP pools this process already runs; and unlike multiprocessing's spawn it never re-runs
the caller's script, which a script without a ``__main__`` guard would suffer. The call and
its value travel as pickles in a temporary folder. If the child cannot start or fails,
:meth:`BackgroundCall.result` computes the value here instead, so the result never depends on
whether a second process was available, and an error is raised here, by the same code.
"""

from __future__ import annotations

import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import time


class BackgroundCall:
    """``fn(*args)`` computed in a child process; :meth:`result` waits for and returns its value.

    ``fn`` must be a module-level function and ``args`` picklable (arrays are). With
    ``background=False`` nothing is started and :meth:`result` calls ``fn`` here (the same
    arithmetic), so small problems skip the child's start (its imports cost more than they save).

    Attributes after :meth:`result`: ``seconds`` (the call's own time), ``where`` ("process",
    "here" or "here after the process failed").
    """

    def __init__(self, fn, *args, background: bool = True):
        self._fn, self._args = fn, args
        self._proc = None
        self._dir = None
        self._value = self._none = object()
        self.where = "here"
        self.seconds = 0.0
        if not background:
            return
        try:
            self._dir = tempfile.mkdtemp(prefix="facepipe-")
            call = os.path.join(self._dir, "call.pickle")
            with open(call, "wb") as fh:
                pickle.dump((fn, args), fh, protocol=pickle.HIGHEST_PROTOCOL)
            self._out = os.path.join(self._dir, "value.pickle")
            self._log = open(os.path.join(self._dir, "stderr.txt"), "wb")
            # the child finds what this process imports (facepipe, and the module of fn) where it does
            env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if isinstance(p, str) and p))
            self._proc = subprocess.Popen([sys.executable, "-m", "facepipe.pipeline.background", call, self._out],
                                          stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log, env=env)
        except (OSError, pickle.PicklingError, TypeError, AttributeError):
            self._cleanup()

    def result(self):
        if self._value is self._none:
            self._value = self._compute()
        return self._value

    def _compute(self):
        if self._proc is not None:
            code = self._proc.wait()
            self._proc = None
            if code == 0 and os.path.isfile(self._out):
                with open(self._out, "rb") as fh:
                    value, self.seconds = pickle.load(fh)
                self._cleanup()
                self.where = "process"
                return value
            self.where = "here after the process failed"
        self._cleanup()
        t0 = time.perf_counter()
        value = self._fn(*self._args)
        self.seconds = time.perf_counter() - t0
        return value

    def cancel(self) -> None:
        """Stop the child (on an error in this process) and remove its files."""
        if self._proc is not None:
            self._proc.kill()
            self._proc.wait()
            self._proc = None
        self._cleanup()

    def _cleanup(self) -> None:
        log = getattr(self, "_log", None)
        if log is not None:
            log.close()
            self._log = None
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    def __del__(self):
        try:
            self.cancel()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass


def _main(call_path: str, out_path: str) -> None:  # pragma: no cover - runs in the child process
    with open(call_path, "rb") as fh:
        fn, args = pickle.load(fh)
    t0 = time.perf_counter()
    value = fn(*args)
    tmp = out_path + ".part"
    with open(tmp, "wb") as fh:
        pickle.dump((value, time.perf_counter() - t0), fh, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, out_path)


if __name__ == "__main__":  # pragma: no cover
    _main(sys.argv[1], sys.argv[2])
