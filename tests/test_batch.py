"""`facepipe batch` on a real Dask cluster: a scheduler and two workers started as processes on
localhost with the ``dask`` command line, a worker killed mid-take, a corrupt take among good
ones; every take's positions.npy compared with a serial `facepipe replay` of it, to the bit."""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from bench.batch_speed import write_takes
from facepipe.errors import InputError
from facepipe.batch.jobs import ATTEMPTS_NAME, ReplayOptions, expand_takes, plan_jobs, worker_threads
from tests.conftest import run_cli

distributed = pytest.importorskip("distributed")

ROOT = Path(__file__).resolve().parents[1]
DASK = Path(sys.executable).with_name("dask")
N_TAKES = 6
N_FRAMES = 40


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    """A small baked sample rig, takes of its motion and their serial replays (NumPy backend)."""
    from facepipe.sample_rig import write_sample_rig

    root = tmp_path_factory.mktemp("batch")
    write_sample_rig(root / "rig", n_vertices=2000, n_frames=N_FRAMES)
    model = root / "model.npz"
    assert run_cli("--quiet", "bake", root / "rig" / "sample.toml", "--no-tune", "-o", model) == 0
    paths = write_takes(root / "rig" / "take.csv", root / "takes", N_TAKES, N_FRAMES)
    for take in paths:
        assert run_cli("--quiet", "replay", take, "-m", model, "-o", root / "serial" / take.stem,
                       "--backend", "numpy") == 0
    return root, model, paths


class Cluster:
    """`dask scheduler` and `dask worker` processes, each in a process group of its own (a worker
    is killed with its nanny)."""

    def __init__(self, root: Path, workers=("wA", "wB")):
        self.port = _free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.logs = root / "logs"
        self.logs.mkdir(exist_ok=True)
        self.env = dict(os.environ, PYTHONPATH=str(ROOT), FACEPIPE_THREADS="1")
        self.scheduler_file = self.logs / "scheduler.json"
        self.procs = {"scheduler": self._start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port",
                                                             str(self.port), "--no-dashboard", "--scheduler-file",
                                                             str(self.scheduler_file)])}
        for name in workers:
            self.procs[name] = self._start(name, ["worker", self.address, "--name", name, "--nthreads", "1",
                                                  "--no-dashboard", "--memory-limit", "2GB", "--death-timeout", "60"])
        with distributed.Client(self.address, timeout=60) as client:
            client.wait_for_workers(len(workers), timeout=120)

    def _start(self, name, args):
        log = open(self.logs / f"{name}.log", "w")
        return subprocess.Popen([str(DASK), *args], stdout=log, stderr=subprocess.STDOUT, env=self.env,
                                cwd=ROOT, start_new_session=True)

    def kill(self, name: str) -> None:
        proc = self.procs.pop(name)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)

    def close(self) -> None:
        for name in list(self.procs):
            proc = self.procs.pop(name)
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=20)
            except ProcessLookupError:
                pass


@pytest.fixture(scope="module")
def cluster(takes):
    if not DASK.is_file():
        pytest.skip(f"no dask command beside {sys.executable}")
    c = Cluster(takes[0])
    try:
        yield c
    finally:
        c.close()


def _errors(out: Path) -> str:
    """What went wrong with the takes of ``out/batch.json``, whole, for an assertion's message."""
    report = json.loads((out / "batch.json").read_text())
    return "\n".join(f"{t['name']}: {t['error']}\n{t.get('traceback') or ''}"
                     + "".join(f"  attempt on {e['worker']}: {e['error']}\n{e['traceback']}" for e in t["attempt_errors"])
                     for t in report["takes"] if t["error"] or t.get("attempt_errors"))


def _same_as_serial(root: Path, out: Path, take: Path) -> bool:
    return np.array_equal(np.load(root / "serial" / take.stem / "positions.npy"),
                          np.load(out / take.stem / "positions.npy"))


# ----------------------------------------------------------------------------- without a cluster


def test_the_benchs_one_process_reference_replays_as_serially(takes, tmp_path):
    """bench.batch_speed's "one process" run (every take in one process, one evaluator, as a
    worker holds it) gives each take's positions as ``facepipe replay`` does, to the byte."""
    from bench.batch_speed import one_process

    root, model, paths = takes
    one_process(paths[:2], model, tmp_path, "numpy")
    for take in paths[:2]:
        assert _same_as_serial(root, tmp_path, take)


def test_takes_from_files_folders_and_patterns(tmp_path):
    for name in ("a.csv", "b.c3d", "notes.md"):
        (tmp_path / name).write_text("x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "c.trc").write_text("x")
    found = expand_takes([tmp_path, str(tmp_path / "sub" / "*.trc"), tmp_path / "a.csv"])
    assert [p.name for p in found] == ["a.csv", "b.c3d", "c.trc"]  # each once, notes.md is no take
    with pytest.raises(InputError, match="matches no file"):
        expand_takes([str(tmp_path / "*.xyz")])
    with pytest.raises(InputError, match="not found"):
        expand_takes([tmp_path / "missing.csv"])
    (tmp_path / "sub" / "a.trc").write_text("x")
    (tmp_path / "sub" / "b.mdd").write_bytes(b"x")
    # takes sharing a stem are named with their format too; the others keep their stem
    jobs = plan_jobs(expand_takes([tmp_path / "a.csv", tmp_path / "sub" / "a.trc", tmp_path / "sub" / "b.mdd"]),
                     tmp_path / "out")
    assert [(j.name, Path(j.out_dir).name) for j in jobs] == [("a_csv", "a_csv"), ("a_trc", "a_trc"), ("b", "b")]
    (tmp_path / "sub" / "a.csv").write_text("x")  # the same file name in two folders: refused
    with pytest.raises(InputError, match="two takes would write"):
        plan_jobs(expand_takes([tmp_path / "a.csv", tmp_path / "sub" / "a.csv"]), tmp_path / "out")


def test_mesh_caches_and_obj_sequences_are_takes(tmp_path):
    (tmp_path / "a.csv").write_text("x")
    (tmp_path / "b.mdd").write_bytes(b"x")
    (tmp_path / "rig.usda").write_text("x")
    seq = tmp_path / "shot_010"
    seq.mkdir()
    for n in (1, 2, 3):
        (seq / f"head_{n:04d}.obj").write_text(f"v 0 0 {n}\n")
    found = expand_takes([tmp_path])
    assert [p.name for p in found] == ["a.csv", "b.mdd", "rig.usda", "shot_010"]  # the sequence is one take
    assert expand_takes([seq]) == [seq.resolve()]  # a folder of OBJ files alone is a sequence
    (seq / "notes.txt").write_text("shot 10, take 3\n")  # notes beside the frames are no take
    assert expand_takes([seq]) == [seq.resolve()]
    assert [p.name for p in expand_takes([tmp_path])] == ["a.csv", "b.mdd", "rig.usda", "shot_010"]
    rig = tmp_path / "rig"  # a rig's meshes (no frame numbers) are no OBJ sequence
    (rig / "expressions").mkdir(parents=True)
    for name in ("neutral.obj", "expressions/smile.obj", "expressions/jawOpen.obj"):
        (rig / name).write_text("v 0 0 0\n")
    (rig / "take.csv").write_text("x")
    assert [p.name for p in expand_takes([rig])] == ["take.csv"]
    (seq / "notes.txt").unlink()
    pattern = expand_takes([str(seq / "head_%04d.obj")])
    jobs = plan_jobs(found, tmp_path / "out")
    assert [j.name for j in jobs] == ["a", "b", "rig", "shot_010"]
    assert plan_jobs(pattern, tmp_path / "out")[0].name == "shot_010"  # a pattern is named after its folder
    with pytest.raises(InputError, match="two takes would write"):
        plan_jobs([seq.resolve(), pattern[0]], tmp_path / "out")
    # a sequence's digest is its frames': a frame changed, the take is another
    before = plan_jobs([seq.resolve()], tmp_path / "out")[0].digest
    assert plan_jobs(pattern, tmp_path / "out")[0].digest == before
    (seq / "head_0002.obj").write_text("v 0 0 7\n")
    assert plan_jobs([seq.resolve()], tmp_path / "out")[0].digest != before
    # a sequence with a frame missing is a take that fails, saying which frame; not the batch's end
    (seq / "head_0004.obj").write_text("v 0 0 4\n")
    (seq / "head_0002.obj").unlink()  # frames 1, 3, 4
    job = plan_jobs([seq.resolve(), found[0]], tmp_path / "out")
    assert job[0].digest is None and "frame 2 of the OBJ sequence is missing" in job[0].error
    assert job[1].error is None and job[1].digest


def test_options_fingerprint_ignores_where_it_runs_only():
    base = ReplayOptions().fingerprint()
    assert ReplayOptions(device="gpu", chunk=64).fingerprint() == base
    assert ReplayOptions(smooth=1.0).fingerprint() != base
    assert ReplayOptions(head_motion="remove").fingerprint() != base
    assert ReplayOptions(large_scale="shell").fingerprint() != base
    assert "large_scale" not in base  # stamps written before caches were takes stay valid


def test_threads_share_the_host_among_its_slots(monkeypatch):
    from facepipe import parallel

    monkeypatch.delenv("FACEPIPE_THREADS", raising=False)
    monkeypatch.setattr(parallel, "available_cpus", lambda: 16)
    monkeypatch.setattr("facepipe.batch.jobs._this_host", lambda: "10.0.0.7")
    assert worker_threads({"10.0.0.7": 4, "10.0.0.8": 1}) == 4
    assert worker_threads({"10.0.0.7": 32}) == 1
    monkeypatch.setenv("FACEPIPE_THREADS", "3")
    assert worker_threads({"10.0.0.7": 4}) == 3


def test_missing_take_is_said_before_any_cluster(tmp_path, capsys):
    code = run_cli("batch", tmp_path / "nothere.csv", "-m", tmp_path / "model.npz", "-o", tmp_path / "out")
    out, err = capsys.readouterr()
    assert code == 2 and "take not found" in err and "nothere.csv" in err
    # nothing said of a cluster, and no progress bar, for a batch that never starts
    assert "cluster" not in out + err and "batch:" not in err
    assert not (tmp_path / "out").exists()


def test_an_export_the_model_cannot_give_is_refused_before_any_take(takes, tmp_path, capsys):
    """Wrinkle maps of a WPSD model, displacement maps of a model without details or without UVs:
    no replay of any take could be exported so, so the batch stops at once (exit 2, nothing
    written) instead of replaying every take and failing each one's export."""
    from facepipe.io.model_file import load_model, save_model

    root, model, paths = takes
    assert run_cli("batch", paths[0], "-m", model, "-o", tmp_path / "w", "--export", "wrinkle") == 2
    assert "wrinkle maps need one blend coefficient" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()
    m = load_model(model)
    arrays = {f.name: getattr(m, f.name) for f in dataclasses.fields(m) if isinstance(getattr(m, f.name), np.ndarray)}
    save_model(tmp_path / "none.npz", arrays, dict(m.meta, method="none"))
    assert run_cli("batch", paths[0], "-m", tmp_path / "none.npz", "-o", tmp_path / "n", "--export", "exr") == 2
    assert "no fine-scale details" in capsys.readouterr().err and not (tmp_path / "n").exists()
    save_model(tmp_path / "no_uvs.npz", {k: v for k, v in arrays.items() if k != "uvs" and k != "polygon_uvs"},
               m.meta)
    assert run_cli("batch", paths[0], "-m", tmp_path / "no_uvs.npz", "-o", tmp_path / "u", "--export", "exr") == 2
    assert "no texture coordinates" in capsys.readouterr().err and not (tmp_path / "u").exists()
    # layered textures need each take's classified footage, which a batch does not make
    assert run_cli("batch", paths[0], "-m", model, "-o", tmp_path / "t", "--export", "textures") == 2
    assert "appearance classify" in capsys.readouterr().err and not (tmp_path / "t").exists()


_MAPPED_BYTES = """
import ctypes, sys
import numpy as np

class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
if sys.argv[1] == "set":
    from facepipe.batch.worker_memory import reuse_freed_arrays
    assert reuse_freed_arrays()
np.ones(2 << 20).sum()  # a chunk's 16 MiB temporary, made and freed
again = np.ones(2 << 20)  # the next chunk's
print(libc.mallinfo2().hblkhd)  # bytes the allocator holds in mappings of their own
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc"
                    or platform.libc_ver()[1] < "2.33", reason="glibc's malloc (mallinfo2) only")
def test_worker_reuses_freed_arrays_despite_the_nannys_trim_threshold():
    """With Dask's MALLOC_TRIM_THRESHOLD_ every 16 MiB array is a mapping of its own (mapped, its
    pages faulted in, unmapped when freed); after reuse_freed_arrays the next one is served from
    the heap, where the freed one was."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), MALLOC_TRIM_THRESHOLD_="65536")

    def mapped_bytes(mode):
        run = subprocess.run([sys.executable, "-c", _MAPPED_BYTES, mode], env=env, capture_output=True,
                             text=True, check=True)
        return int(run.stdout.split()[-1])

    assert mapped_bytes("plain") >= 16 << 20
    assert mapped_bytes("set") < 16 << 20


def test_unreachable_scheduler_is_a_cluster_failure(takes, tmp_path):
    root, model, paths = takes
    out = tmp_path / "out"
    code = run_cli("--quiet", "batch", paths[0], "-m", model, "-o", out, "--scheduler",
                   f"tcp://127.0.0.1:{_free_port()}", "--connect-timeout", "2")
    assert code == 1
    report = json.loads((out / "batch.json").read_text())
    assert report["cluster_error"] and report["takes"][0]["status"] == "failed"


_ATTEMPT = """
import json, pickle, sys, time
from pathlib import Path

from facepipe.batch import jobs
from facepipe.io import npy_stream

args, flags, role = pickle.loads(Path(sys.argv[1]).read_bytes()), Path(sys.argv[2]), sys.argv[3]
if role == "first":  # stops after its first rows until told to go on
    write = npy_stream.NpyWriter.write

    def write_then_wait(self, rows):
        write(self, rows)
        if not (flags / "writing").exists():
            (flags / "writing").touch()
            deadline = time.monotonic() + 300
            while not (flags / "go").exists() and time.monotonic() < deadline:
                time.sleep(0.01)

    npy_stream.NpyWriter.write = write_then_wait
try:
    result = {"record": jobs.replay_take_task(*args)}
except Exception as exc:
    result = {"raised": f"{exc.__class__.__name__}: {exc}"}
(flags / f"{role}.json").write_text(json.dumps(result))
"""


@pytest.mark.slow
@pytest.mark.parametrize("force", [False, True])
def test_two_attempts_at_one_take_at_once_leave_it_complete_once(takes, tmp_path, force):
    """Dask runs a take again while an attempt it gave up on still runs (a worker it lost but
    that lives on): the second attempt starts while the first is writing positions.npy. Both
    end well, the take is replayed once, its outputs are complete and a serial replay's, and
    nothing half-written is left. With --force the second attempt, of the same batch, keeps
    what the first completed rather than replaying it again."""
    import pickle

    from facepipe.batch.jobs import ATTEMPTS_NAME, STAMP_NAME, ModelRef, file_digest

    root, model, paths = takes
    out, flags = tmp_path / "out", tmp_path / "flags"
    flags.mkdir()
    job = plan_jobs([paths[1]], out, "batch-1")[0] if force else plan_jobs([paths[1]], out)[0]
    args = (job, ModelRef(str(model.resolve()), file_digest(model)), ReplayOptions(backend="numpy"), (), force)
    (flags / "args.pickle").write_bytes(pickle.dumps(args))
    env = dict(os.environ, PYTHONPATH=str(ROOT), FACEPIPE_THREADS="1")

    def attempt(role):
        return subprocess.Popen([sys.executable, "-c", _ATTEMPT, str(flags / "args.pickle"), str(flags), role],
                                env=env, cwd=ROOT)

    def started() -> int:
        log = out / paths[1].stem / ATTEMPTS_NAME
        return sum('"worker"' in line for line in log.read_text().splitlines()) if log.is_file() else 0

    first = attempt("first")
    deadline = time.monotonic() + 300  # a bound on a hung test only
    while not (flags / "writing").exists() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    second = attempt("second")
    while started() < 2 and second.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    (flags / "go").touch()
    assert first.wait(timeout=300) == 0 and second.wait(timeout=300) == 0
    results = [json.loads((flags / f"{role}.json").read_text()) for role in ("first", "second")]
    assert all("record" in r for r in results), results
    records = [r["record"] for r in results]
    assert [r["status"] for r in records] == ["ok", "ok"] and [r["frames"] for r in records] == [N_FRAMES] * 2
    assert [r["replayed"] for r in records] == [True, False]  # the second kept the first's replay
    assert records[1]["attempts"] == 2
    take_dir = out / paths[1].stem
    assert _same_as_serial(root, out, paths[1])
    stamp = json.loads((take_dir / STAMP_NAME).read_text())
    assert stamp["frames"] == N_FRAMES and stamp["take_digest"] == job.digest
    assert json.loads((take_dir / "replay.json").read_text())["frames"] == N_FRAMES
    assert not list(take_dir.rglob(".*.part*"))


@pytest.mark.slow
def test_an_attempts_error_is_reported_whole(takes, tmp_path, monkeypatch):
    """A disk error in the middle of positions.npy is raised as itself (Dask runs the take again)
    and logged with its traceback; the attempt that completes the take reports it. An internal
    error is reported with its traceback, and with the error it was raised while handling."""
    import errno

    from facepipe import parallel
    from facepipe.batch import jobs
    from facepipe.io import npy_stream

    root, model, paths = takes
    monkeypatch.setattr(jobs, "reuse_freed_arrays", lambda: False)  # (this test's process keeps its allocator)
    monkeypatch.setattr(parallel, "_override", parallel._override)
    for name in jobs.POCL_THREADS_ENV:
        monkeypatch.setenv(name, "1")
    job = plan_jobs([paths[2]], tmp_path / "out", "batch-1")[0]
    args = (job, jobs.ModelRef(str(model.resolve()), jobs.file_digest(model)), ReplayOptions(backend="numpy"))
    real_write, calls = os.write, []

    def failing_write(fd, data):
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(errno.EIO, "Input/output error")
        return real_write(fd, data)

    with monkeypatch.context() as patch:
        patch.setattr(npy_stream.os, "write", failing_write)
        with pytest.raises(OSError, match="Input/output error"):
            jobs.replay_take_task(*args)
    record = jobs.replay_take_task(*args)
    assert record["status"] == "ok" and record["attempts"] == 2 and record["replayed"]
    [error] = record["attempt_errors"]
    assert error["error"].startswith("OSError: [Errno 5] Input/output error (")
    assert "_write_all" in error["traceback"] and "replay_windows" in error["traceback"]
    assert _same_as_serial(root, tmp_path / "out", paths[2])

    def broken_report(*a, **k):
        try:
            raise KeyError("frames")
        except KeyError:
            raise ValueError("the report could not be made")

    monkeypatch.setattr(jobs, "replay_into", broken_report)
    record = jobs.replay_take_task(dataclasses.replace(job, batch="batch-2"), *args[1:], force=True)
    assert record["status"] == "failed" and record["error"].startswith(
        "internal error ValueError: the report could not be made (test_batch.py:")
    assert "raised while handling KeyError: 'frames'" in record["error"]
    assert "KeyError: 'frames'" in record["traceback"] and "During handling" in record["traceback"]


# ----------------------------------------------------------------------------- on a real cluster


@pytest.mark.slow
def test_corrupt_take_is_reported_and_the_rest_go_on(takes, cluster, tmp_path):
    root, model, paths = takes
    bad = tmp_path / "takes" / "broken.csv"
    bad.parent.mkdir()
    bad.write_text(paths[0].read_text().splitlines()[0] + "\n0,0.0,not a number\n")
    good = paths[:3]
    out = tmp_path / "out"
    args = ["--quiet", "batch", *good, bad, "-m", model, "-o", out, "--scheduler", cluster.address,
            "--backend", "numpy"]
    assert run_cli(*args) == 2
    report = json.loads((out / "batch.json").read_text())
    status = {t["name"]: t for t in report["takes"]}
    assert report["failed"] == [str(bad)], _errors(out)
    assert status["broken"]["status"] == "failed" and "broken.csv" in status["broken"]["error"]
    assert all(status[t.stem]["status"] == "ok" and status[t.stem]["frames"] == N_FRAMES for t in good)
    assert all(_same_as_serial(root, out, t) for t in good)

    # again: the good takes are complete, so skipped untouched; --force replays them
    mtime = (out / good[0].stem / "positions.npy").stat().st_mtime_ns
    assert run_cli(*args) == 2
    report = json.loads((out / "batch.json").read_text())
    assert [t["status"] for t in report["takes"]] == ["skipped"] * 3 + ["failed"]
    assert (out / good[0].stem / "positions.npy").stat().st_mtime_ns == mtime
    assert run_cli("--quiet", "batch", *good, "-m", model, "-o", out, "--scheduler-file", cluster.scheduler_file,
                   "--backend", "numpy", "--force") == 0, _errors(out)
    report = json.loads((out / "batch.json").read_text())
    assert [t["status"] for t in report["takes"]] == ["ok"] * 3 and all(_same_as_serial(root, out, t) for t in good)
    assert report["scheduler"] == cluster.address


def test_mesh_caches_replay_as_serially_beside_marker_takes(takes, cluster, tmp_path):
    """An MDD cache and an OBJ sequence (folder) batched with a marker take: each is the serial
    `facepipe replay` of it, to the bit (BLAS on one thread, as on Dask's workers); a batch again
    skips them, and --large-scale shell (an option of the caches') replays them again."""
    from threadpoolctl import threadpool_limits

    from facepipe.io.mesh_read import load_mesh
    from facepipe.io.mesh_write import save_obj
    from facepipe.io.point_caches import read_mdd

    root, model, paths = takes
    mdd = root / "rig" / "take_smooth.mdd"
    rest = load_mesh(root / "rig" / "neutral.obj")
    seq = tmp_path / "shot_obj"
    seq.mkdir()
    for n, frame in enumerate(read_mdd(mdd)[1][:8]):
        save_obj(seq / f"shot_{n + 1:04d}.obj", rest, frame)
    serial = {}
    for take, mode in ((mdd, "take"), (seq, "take"), (mdd, "shell")):
        dest = tmp_path / "serial" / f"{take.name}-{mode}"
        with threadpool_limits(1):
            assert run_cli("--quiet", "replay", take, "-m", model, "-o", dest, "--backend", "numpy",
                           "--large-scale", mode) == 0
        serial[take.name, mode] = np.load(dest / "positions.npy")
    out = tmp_path / "out"
    args = ["--quiet", "batch", paths[0], mdd, seq, "-m", model, "-o", out, "--scheduler", cluster.address,
            "--backend", "numpy"]
    assert run_cli(*args) == 0, _errors(out)
    report = json.loads((out / "batch.json").read_text())
    assert [(t["name"], t["status"], t["frames"]) for t in report["takes"]] == [
        (paths[0].stem, "ok", N_FRAMES), ("take_smooth", "ok", N_FRAMES), ("shot_obj", "ok", 8)]
    assert _same_as_serial(root, out, paths[0])
    assert np.array_equal(np.load(out / "take_smooth" / "positions.npy"), serial["take_smooth.mdd", "take"])
    assert np.array_equal(np.load(out / "shot_obj" / "positions.npy"), serial["shot_obj", "take"])
    cache_report = json.loads((out / "take_smooth" / "replay.json").read_text())
    assert cache_report["cache"]["large_scale"] == "take" and "bands" in cache_report["cache"]
    assert run_cli(*args) == 0
    assert [t["status"] for t in json.loads((out / "batch.json").read_text())["takes"]] == ["skipped"] * 3
    assert run_cli(*args[:5], "-m", model, "-o", out, "--scheduler", cluster.address, "--backend", "numpy",
                   "--large-scale", "shell") == 0, _errors(out)
    assert np.array_equal(np.load(out / "take_smooth" / "positions.npy"), serial["take_smooth.mdd", "shell"])


def test_2d_takes_replay_as_serially_with_the_shoots_camera(takes, cluster, tmp_path):
    """A 2D landmark take (OpenFace CSV) of the rig's replayed face, filmed by a camera, batched
    with --camera and --landmarks: the serial `facepipe replay` of it, to the bit, with its video
    record; without --camera it fails saying what to give, the other takes go on."""
    from threadpoolctl import threadpool_limits

    from facepipe.core.camera import project_distorted
    from facepipe.io.camera_file import write_camera
    from tests.test_video import CAMERA, FACING, _openface_text

    root, model, paths = takes
    face = np.load(root / "serial" / paths[0].stem / "positions.npy").astype(np.float64)
    rest = face[0]
    front = np.flatnonzero(rest[:, 2] > np.percentile(rest[:, 2], 50))
    vertices = front[np.linspace(0, len(front) - 1, 30).astype(int)]
    (tmp_path / "landmarks.csv").write_text("name,vertex\n" + "".join(f"{i},{v}\n" for i, v in enumerate(vertices)))
    camera = tmp_path / "camera.yml"
    write_camera(camera, CAMERA)
    seen = np.einsum("ij,tvj->tvi", FACING, face[:, vertices]) + np.array([0.0, 0.0, 60.0])
    take = tmp_path / "shot_2d.csv"
    times = np.arange(len(face)) / 30.0
    take.write_text(_openface_text(np.arange(1, len(face) + 1), times, project_distorted(CAMERA, seen)))
    with threadpool_limits(1):
        assert run_cli("--quiet", "replay", take, "-m", model, "-o", tmp_path / "serial", "--backend", "numpy",
                       "--camera", camera, "--landmarks", tmp_path / "landmarks.csv") == 0
    out = tmp_path / "out"
    args = ["--quiet", "batch", take, paths[1], "-m", model, "-o", out, "--scheduler", cluster.address,
            "--backend", "numpy"]
    assert run_cli(*args) == 2  # no camera: that take fails, saying what to give; the marker take is done
    status = {t["name"]: t for t in json.loads((out / "batch.json").read_text())["takes"]}
    assert status["shot_2d"]["status"] == "failed" and "--camera" in status["shot_2d"]["error"]
    assert status[paths[1].stem]["status"] == "ok"
    assert not (out / "shot_2d" / "positions.npy").exists() and not (out / "shot_2d" / "replay.json").exists()
    assert run_cli(*args, "--camera", camera, "--landmarks", tmp_path / "landmarks.csv") == 0, _errors(out)
    assert np.array_equal(np.load(out / "shot_2d" / "positions.npy"), np.load(tmp_path / "serial" / "positions.npy"))
    assert (out / "shot_2d" / "video.npz").is_file()
    report = json.loads((out / "shot_2d" / "replay.json").read_text())
    assert report["coordinates"].startswith("camera") and report["video"]["reprojection_px"]["mean"] < 1.0
    assert run_cli("--quiet", "batch", take, "-m", model, "-o", out, "--backend", "numpy", "--camera",
                   tmp_path / "nothere.yml") == 2  # a missing camera is said before any cluster


@pytest.mark.slow
def test_scheduler_from_the_environment_and_model_read_once_per_worker(takes, cluster, tmp_path, monkeypatch):
    root, model, paths = takes
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", cluster.address)
    out = tmp_path / "out"
    assert run_cli("--quiet", "batch", *paths, "-m", model, "-o", out, "--backend", "numpy") == 0
    report = json.loads((out / "batch.json").read_text())
    assert report["cluster"] == f"scheduler {cluster.address}"
    assert all(t["status"] == "ok" for t in report["takes"])
    loads = [t["worker"] for t in report["takes"] if t["model_loaded"]]
    # the workers of the earlier tests hold this model already: no worker reads it twice
    assert len(loads) == len(set(loads)) <= 2

    # an export asked for later: the replays are kept, only the export is made, as `facepipe export` makes it
    mtime = (out / paths[0].stem / "positions.npy").stat().st_mtime_ns
    assert run_cli("--quiet", "batch", *paths[:2], "-m", model, "-o", out, "--backend", "numpy", "--export", "obj") == 0
    report = json.loads((out / "batch.json").read_text())
    assert [(t["status"], t["replayed"]) for t in report["takes"]] == [("ok", False)] * 2
    assert (out / paths[0].stem / "positions.npy").stat().st_mtime_ns == mtime
    assert run_cli("--quiet", "export", root / "serial" / paths[0].stem, "--format", "obj", "-o", tmp_path / "obj") == 0
    ours = sorted((out / paths[0].stem / "obj").iterdir())
    assert [p.name for p in ours] == sorted(p.name for p in (tmp_path / "obj").iterdir())
    assert all(p.read_bytes() == (tmp_path / "obj" / p.name).read_bytes() for p in ours)
    assert run_cli("--quiet", "batch", *paths[:2], "-m", model, "-o", out, "--backend", "numpy", "--export", "obj") == 0
    assert [t["status"] for t in json.loads((out / "batch.json").read_text())["takes"]] == ["skipped"] * 2


@pytest.mark.slow
def test_killed_worker_take_runs_elsewhere_and_the_batch_completes(takes, cluster, tmp_path):
    root, model, paths = takes
    out = tmp_path / "out"
    result = {}

    def batch():
        result["code"] = run_cli("--quiet", "batch", *paths, "-m", model, "-o", out, "--scheduler",
                                 cluster.address, "--backend", "numpy", "--export", "pc2")

    runner = threading.Thread(target=batch)
    runner.start()
    killed_take = None
    deadline = time.monotonic() + 180
    while killed_take is None and runner.is_alive() and time.monotonic() < deadline:
        for log in out.glob(f"*/{ATTEMPTS_NAME}"):
            lines = log.read_text().splitlines()
            # wA's attempt is under way and positions.npy half-written: kill it mid-replay
            if lines and '"worker": "wA"' in lines[-1] and list(log.parent.glob(".positions.npy.*")):
                cluster.kill("wA")
                killed_take = log.parent.name
                break
        time.sleep(0.005)
    runner.join(timeout=300)
    assert not runner.is_alive()
    assert killed_take is not None, "worker wA never started a take"
    assert result["code"] == 0, _errors(out)
    report = json.loads((out / "batch.json").read_text())
    assert report["totals"]["ok"] == N_TAKES and report["totals"]["retried"] >= 1
    record = next(t for t in report["takes"] if t["name"] == killed_take)
    assert record["attempts"] >= 2 and record["attempt_workers"][0] == "wA" and record["worker"] == "wB"
    assert all(_same_as_serial(root, out, t) for t in paths)
    assert all((out / t.stem / f"{t.stem}.pc2").is_file() for t in paths)
    assert not list(out.rglob(".*.part*"))  # the killed attempt's temporary files are gone


@pytest.mark.slow
def test_local_cluster_by_default(takes, tmp_path, monkeypatch):
    root, model, paths = takes
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    out = tmp_path / "out"
    assert run_cli("--quiet", "batch", str(paths[0].parent / "take_00[01].csv"), "-m", model, "-o", out,
                   "--workers", "2", "--backend", "numpy") == 0
    report = json.loads((out / "batch.json").read_text())
    assert report["cluster"] == "local cluster of 2 workers" and report["workers"] == 2
    assert [t["status"] for t in report["takes"]] == ["ok", "ok"]
    assert all(_same_as_serial(root, out, t) for t in paths[:2])


@pytest.mark.slow
def test_lost_scheduler_is_a_cluster_failure(takes, tmp_path):
    root, model, paths = takes
    if not DASK.is_file():
        pytest.skip(f"no dask command beside {sys.executable}")
    own = Cluster(tmp_path, workers=("wC",))
    out = tmp_path / "out"
    result = {}
    try:
        runner = threading.Thread(target=lambda: result.update(code=run_cli(
            "--quiet", "batch", *paths, "-m", model, "-o", out, "--scheduler", own.address, "--backend", "numpy",
            "--connect-timeout", "3")))
        runner.start()
        deadline = time.monotonic() + 120
        while not list(out.glob(f"*/{ATTEMPTS_NAME}")) and time.monotonic() < deadline:
            time.sleep(0.01)
        own.kill("scheduler")
        runner.join(timeout=180)
        assert not runner.is_alive()
    finally:
        own.close()
    assert result["code"] == 1
    report = json.loads((out / "batch.json").read_text())
    assert report["cluster_error"] and report["totals"]["failed"] >= 1
