"""Many takes replayed (and exported) against one model, one task per take on a Dask cluster.

The client side (:func:`plan_batch`, :func:`run_batch`) finds the takes, fingerprints the model
file, the takes and the options, skips takes whose folder already holds what this batch would
write, submits the rest and gathers one record per take into ``OUT/batch.json``. The worker side
(:func:`replay_take_task`) replays one take into ``OUT/<take stem>/`` exactly as ``facepipe
replay`` does (the same reading, preparation and evaluator), then exports it.

The model travels by path, never inside a task: every worker process loads it once from the
shared file system, checks it has the client's digest, and keeps it (and its evaluator, whose
OpenCL kernels are built once) for every later take with that digest.

A take's folder is complete only once ``batch_take.json`` is written, last, atomically; the
outputs before it are written atomically too. Attempts at one take never overlap in its folder
(:mod:`facepipe.batch.take_lock`): Dask can run a take again while an attempt it gave up on still
runs, and that later attempt waits, then keeps what the earlier one of its batch completed. A
worker killed mid-take leaves at most temporary ``.NAME.part`` files (removed by the next attempt)
and an attempt line in ``batch_attempts.jsonl``; an attempt that fails on an error adds that
error and its traceback there. The attempt that completes the take reports them all
(``attempts``, ``attempt_workers``, ``attempt_errors`` in ``batch.json``).
"""

from __future__ import annotations

import asyncio
import contextlib
import glob
import hashlib
import json
import os
import socket
import threading
from collections import Counter
import time
import traceback
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path

from distributed import KilledWorker, as_completed, get_worker
from distributed.comm import get_address_host

from facepipe import parallel
from facepipe.errors import InputError, describe_system_error
from facepipe.export import registry as export_registry
from facepipe.export.registry import ExportOptions
from facepipe.io.atomic import atomic_path
from facepipe.io.camera_file import read_camera
from facepipe.io.model_file import load_model
from facepipe.io.replay_folder import ReplayDir
from facepipe.mocap import registry as take_registry
from facepipe.mocap.registry import mesh_cache_format
from facepipe.mocap import parse_frame_slice
from facepipe.mocap.landmarks2d import is_landmark_take
from facepipe.mocap.mesh_cache import NUMBERED_OBJ, obj_sequence_files
from facepipe.mocap.marker_take import MarkerTakeOptions, read_marker_take
from facepipe.batch.cluster import ClusterError, ClusterSpec, open_client, slots_by_host
from facepipe.batch.take_lock import take_lock
from facepipe.batch.worker_memory import reuse_freed_arrays
from facepipe.pipeline.backend import cache_evaluator, marker_evaluator
from facepipe.pipeline.cache_replay import replay_mesh_cache
from facepipe.pipeline.replay import replay_windows
from facepipe.pipeline.video_replay import landmark_map_for, replay_landmark_take

STAMP_NAME = "batch_take.json"
ATTEMPTS_NAME = "batch_attempts.jsonl"
REPORT_NAME = "batch.json"
# PoCL's CPU driver's threads per process (read when the driver starts): PoCL 3's pthread
# device, and the name PoCL 4 and later read
POCL_THREADS_ENV = ("POCL_MAX_PTHREAD_COUNT", "POCL_CPU_MAX_CU_COUNT")
# the options of mesh caches and 2D takes: in a fingerprint only where given (stamps written
# before they were options stay valid)
NEWER_OPTIONS = ("large_scale", "rest_frame", "cache_fps", "lift", "min_confidence")


# ============================================================================= what a take's task gets


@dataclass(frozen=True)
class ReplayOptions:
    """``facepipe replay``'s options for the takes of a batch (their defaults are replay's): the
    marker takes' (subject, cleaning, stabilising, neutral), the mesh caches' (large_scale,
    rest_frame, cache_fps) and the 2D takes' (camera, landmarks, lift, min_confidence), each
    applied to the takes it concerns."""

    backend: str = "auto"
    device: str | None = None
    frames: str | None = None
    chunk: int = 32
    head_motion: str = "keep"
    save_large: bool = False
    neutral_frame: int | None = None
    neutral_take: str | None = None
    take_units: str | None = None
    subject: str | None = None
    stabilise: bool = True
    clean: bool = True
    smooth: float = 0.0
    large_scale: str | None = None  # mesh caches: "take" (None: the default) or "shell"
    rest_frame: int | None = None
    cache_fps: float | None = None
    camera: str | None = None  # 2D landmark takes: the camera's calibration
    landmarks: str | None = None  # 2D takes: name,vertex map (None: the model's)
    lift: str | None = None  # 2D takes: "model" (None: the default) or "heuristic"
    min_confidence: float | None = None  # 2D takes: None: replay's default

    def fingerprint(self) -> dict:
        """What decides the outputs: every option but where the evaluation runs (the backend and
        device give the same positions to rounding; chunk none at all), and the neutral take's
        content rather than its path (the camera's and landmark map's too). The mesh caches' and 2D
        takes' options count where given (a batch of marker takes keeps the stamps it wrote before
        they were options)."""
        key = {k: v for k, v in asdict(self).items()
               if k not in ("device", "chunk", "neutral_take", "camera", "landmarks")
               and not (k in NEWER_OPTIONS and v is None)}
        key["neutral_take_digest"] = file_digest(self.neutral_take) if self.neutral_take else None
        for name in ("camera", "landmarks"):
            if getattr(self, name):
                key[f"{name}_digest"] = file_digest(getattr(self, name))
        return key

    def marker_take(self) -> MarkerTakeOptions:
        """The options of reading and preparing the take, as replay's."""
        return MarkerTakeOptions(take_units=self.take_units, subject=self.subject, clean=self.clean,
                                 stabilise=self.stabilise, neutral_frame=self.neutral_frame,
                                 neutral_take=self.neutral_take, frames=self.frames, smooth=self.smooth)


@dataclass(frozen=True)
class ModelRef:
    """A model by path on storage every worker sees, and the client's digest of that file."""

    path: str
    digest: str


@dataclass(frozen=True)
class TakeJob:
    """One take of the batch: its file, digest and output folder, and the batch's id; ``error``:
    why it cannot run at all (an OBJ sequence with a frame missing), reported as it failing."""

    take: str
    name: str
    out_dir: str
    digest: str | None
    batch: str | None = None
    error: str | None = None


@dataclass
class TakeRecord:
    """A take's line in ``batch.json``."""

    take: str
    name: str
    output: str
    status: str  # ok | skipped | failed
    frames: int | None = None
    seconds: float | None = None
    worker: str | None = None
    error: str | None = None
    traceback: str | None = None  # where the error is not the input's: the whole exception, chained ones too
    attempts: int = 0
    attempt_workers: list = field(default_factory=list)
    attempt_errors: list = field(default_factory=list)  # {worker, error, traceback} of attempts that erred
    replayed: bool = False
    model_loaded: bool = False  # this take's worker process read the model for it (once per process)
    exports: dict = field(default_factory=dict)


def file_digest(path, block: int = 1 << 22) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(block):
            h.update(chunk)
    return h.hexdigest()


# ============================================================================= the takes and the plan


def expand_takes(specs) -> list[Path]:
    """Takes from files, folders and glob patterns, each once. A folder is a take of its own when
    it is an OBJ sequence (numbered OBJ files and no other take; text files beside them, such as
    notes, are not read as takes there), else its takes are its take files and mesh caches
    (sorted) and its subfolders that are OBJ sequences; a ``frame_%04d.obj`` pattern is an OBJ
    sequence. OBJ files without frame numbers (a rig's neutral and expressions) are no take."""
    suffixes = {s for fmt in take_registry.FORMATS.values() for s in fmt.suffixes}
    suffixes |= {s for fmt in take_registry.MESH_CACHES.values() if fmt.match is None for s in fmt.suffixes}
    found: list[Path] = []
    for spec in specs:
        spec = str(spec)
        path = Path(spec)
        if path.is_dir():
            files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in suffixes)
            if all(p.suffix.lower() == ".txt" for p in files) and _is_obj_folder(path):
                matches = [path]
            else:
                matches = sorted(files + [p for p in path.iterdir() if p.is_dir() and _is_obj_folder(p)])
            if not matches:
                raise InputError(f"no takes ({', '.join(sorted(suffixes))} files, or folders of an OBJ sequence) in "
                                 "this folder", path=path)
        elif path.is_file() or (not path.exists() and mesh_cache_format(path) is not None):  # (an OBJ pattern)
            matches = [path]
        elif glob.has_magic(spec):
            matches = sorted(Path(p) for p in glob.glob(spec, recursive=True) if Path(p).is_file())
            if not matches:
                raise InputError(f"the pattern {spec!r} matches no file")
        else:
            raise InputError("take not found", path=path)
        found.extend(matches)
    unique = list(dict.fromkeys(p.resolve() for p in found))
    if not unique:
        raise InputError("no takes given", hint="name take files, folders of takes or glob patterns")
    return unique


def _is_obj_folder(path: Path) -> bool:
    """Whether a folder holds numbered OBJ files (name_0001.obj …): an OBJ sequence."""
    return any(p.is_file() and NUMBERED_OBJ.match(p.name) for p in path.iterdir())


def take_name(take: Path) -> str:
    """A take's name in the batch (its output folder): a file's stem, an OBJ sequence's folder."""
    if take.is_dir():
        return take.name
    if not take.exists():  # an OBJ sequence's pattern
        return take.parent.name
    return take.stem


def take_digest(take: Path) -> str:
    """SHA-256 of a take: its file's bytes, or an OBJ sequence's files (names and bytes, in frame order)."""
    if take.is_file():
        return file_digest(take)
    h = hashlib.sha256()
    for number, path in obj_sequence_files(take):
        h.update(f"{number}:{path.name}:{file_digest(path)}".encode())
    return h.hexdigest()


def plan_jobs(takes: list[Path], out: Path, batch: str | None = None) -> list[TakeJob]:
    """A job per take of the batch ``batch``, its folder ``out/<name>``. Files that share a stem with
    another take (a shot's marker take and its rig's cache, ``shot.c3d`` and ``shot.mdd``) are
    named with their format too (``shot_c3d``, ``shot_mdd``); two takes still of one name (the
    same file name in two folders) are refused."""
    stems = Counter(take_name(take) for take in takes)
    by_name: dict[str, Path] = {}
    for take in takes:
        name = take_name(take)
        if stems[name] > 1 and take.is_file() and take.suffix:
            name = f"{name}_{take.suffix[1:].lower()}"
        if name in by_name:
            same = f" (both named {take.name})" if take.name == by_name[name].name else ""
            raise InputError(f"two takes would write to {out / name}{same}: {by_name[name]} and {take}",
                             hint="batch them into different -o folders, or rename one")
        by_name[name] = take
    jobs = []
    for name, take in by_name.items():
        try:
            jobs.append(TakeJob(str(take), name, str(out / name), take_digest(take), batch))
        except InputError as exc:  # this take alone is bad: the others go on
            jobs.append(TakeJob(str(take), name, str(out / name), None, batch, error=str(exc)))
    return jobs


def export_destination(out_dir: Path, name: str, fmt: str) -> Path:
    """Where a take's export in ``fmt`` goes: a folder named after the format, or a file named
    after the take with the format's first suffix."""
    suffixes = export_registry.get_format(fmt).suffixes
    return out_dir / fmt if not suffixes else out_dir / f"{name}{suffixes[0]}"


def _read_stamp(out_dir: Path) -> dict | None:
    try:
        return json.loads((Path(out_dir) / STAMP_NAME).read_text())
    except (OSError, ValueError):
        return None


def _replay_matches(stamp: dict | None, job: TakeJob, model: ModelRef, options_key: dict) -> bool:
    out_dir = Path(job.out_dir)
    return (stamp is not None and stamp.get("model_digest") == model.digest and stamp.get("take_digest") == job.digest
            and stamp.get("options") == options_key and (out_dir / "positions.npy").is_file()
            and (out_dir / "replay.json").is_file())


def _exports_left(stamp: dict | None, job: TakeJob, exports: tuple[str, ...]) -> list[str]:
    done = (stamp or {}).get("exports", {})
    out_dir = Path(job.out_dir)
    return [fmt for fmt in exports
            if fmt not in done or not export_destination(out_dir, job.name, fmt).exists()]


def skipped_record(job: TakeJob, model: ModelRef, options_key: dict, exports: tuple[str, ...]) -> TakeRecord | None:
    """The record of a take whose folder already holds this batch's outputs, else None."""
    stamp = _read_stamp(Path(job.out_dir))
    if not _replay_matches(stamp, job, model, options_key) or _exports_left(stamp, job, exports):
        return None
    return TakeRecord(job.take, job.name, job.out_dir, "skipped", frames=stamp.get("frames"),
                      exports={fmt: stamp["exports"][fmt] for fmt in exports})


# ============================================================================= on the worker

_cache_lock = threading.Lock()
_model_cache: dict = {}  # digest -> Model (one model at a time)
_evaluator_cache: dict = {}  # (digest, backend, device, chunk) -> (evaluator, lock, note)


def worker_threads(slots_by_host: dict[str, int] | None) -> int:
    """Threads for one take on this worker: FACEPIPE_THREADS where set, else this host's CPUs
    shared among the task slots (worker processes × their threads) the cluster has on it."""
    if parallel._count_from_env(parallel.THREADS_ENV) is not None:
        return parallel.thread_count()
    slots = (slots_by_host or {}).get(_this_host())
    if not slots:
        return parallel.thread_count()
    return max(1, parallel.available_cpus() // slots)


def _this_host() -> str:
    try:
        return get_address_host(get_worker().address)
    except ValueError:  # not on a worker
        return socket.gethostname()


def _worker_name() -> str:
    try:
        worker = get_worker()
        return str(worker.name if worker.name is not None else worker.address)
    except ValueError:  # not on a worker
        return f"{socket.gethostname()}:{os.getpid()}"


def cached_model(ref: ModelRef):
    """(model, whether it was read now): the model of ``ref``, read once per process; the file
    this worker sees must be the client's (same digest), or the take fails saying so."""
    with _cache_lock:
        model = _model_cache.get(ref.digest)
        if model is not None:
            return model, False
        digest = file_digest(ref.path) if Path(ref.path).is_file() else None
        if digest != ref.digest:
            raise InputError(f"the model file as worker {_worker_name()} sees it is not the client's "
                             f"(digest {digest and digest[:12]} ≠ {ref.digest[:12]})", path=ref.path,
                             hint="workers must read the model and write OUT on storage they share with "
                                  "the client, at the same paths")
        _model_cache.clear()  # one model per process: a batch with another model replaces it
        _evaluator_cache.clear()
        model = _model_cache[ref.digest] = load_model(ref.path)
        return model, True


def make_evaluator(model, backend: str, device: str | None, chunk: int):
    """The replay evaluator as ``facepipe replay`` chooses it, and a note when auto fell back."""
    notes = []
    evaluator = marker_evaluator(model, backend, device, chunk, note=notes.append)
    return evaluator, (notes[0] if notes else None)


def cached_evaluator(ref: ModelRef, model, options: ReplayOptions):
    """(evaluator, lock, note): one per process and model, shared by the takes it runs (a take
    holds the lock while it evaluates, so a worker with several threads never interleaves two)."""
    key = (ref.digest, options.backend, options.device, options.chunk)
    with _cache_lock:
        entry = _evaluator_cache.get(key)
        if entry is None:
            evaluator, note = make_evaluator(model, options.backend, options.device, options.chunk)
            entry = _evaluator_cache[key] = (evaluator, threading.Lock(), note)
        return entry


@contextlib.contextmanager
def _held_evaluator(model_ref: ModelRef, model, options: ReplayOptions):
    """This process's marker evaluator for the model and the note of its choice, held for one take
    (another thread's take waits) with its counters reset."""
    evaluator, lock, note = cached_evaluator(model_ref, model, options)
    with lock:
        _reset_counters(evaluator)
        yield evaluator, note


def _reset_counters(evaluator) -> None:
    # the counters replay.json reports are per take; a shared evaluator would add them up
    evaluator.stage_seconds = dict.fromkeys(evaluator.stage_seconds, 0.0)
    for owner in (evaluator, getattr(evaluator, "details", None)):
        gate = getattr(owner, "gate", None)
        if gate is not None and hasattr(gate, "unconverged_fits"):
            gate.unconverged_fits = 0


def replay_into(take_path: str, out_dir: Path, model, model_ref: ModelRef, options: ReplayOptions, extra: dict) -> dict:
    """Replay a take (markers, a mesh cache or a 2D landmark take) into ``out_dir`` as ``facepipe
    replay`` does; its replay.json report. The marker evaluator is this process's for the model
    (held while it evaluates); a mesh cache replayed as a take has an evaluator of its own."""
    if mesh_cache_format(take_path) is not None:
        return _replay_cache(take_path, out_dir, model, model_ref, options, extra)
    if is_landmark_take(take_path):
        return _replay_2d(take_path, out_dir, model, model_ref, options, extra)
    with _held_evaluator(model_ref, model, options) as (evaluator, note):
        extra = {"batch": dict(extra["batch"], note=note)}
        marker_take = read_marker_take(take_path, model, options.marker_take())
        result = replay_windows(model, marker_take.prepared.windows(), marker_take.take.frames, marker_take.take.times,
                                out_dir, chunk=options.chunk, evaluator=evaluator, head_motion=options.head_motion,
                                extra_report=lambda: {**marker_take.report(), **extra}, save_large=options.save_large)
    return result.report


def _replay_cache(take_path: str, out_dir: Path, model, model_ref: ModelRef, options: ReplayOptions,
                  extra: dict) -> dict:
    """A mesh cache replayed as ``facepipe replay CACHE`` does: as a take (an evaluator of its own,
    OpenCL where the backend allows) or through the shell (this process's marker evaluator)."""
    mode = options.large_scale or "take"
    batch = dict(extra["batch"], note=None)  # replay.json's, filled in before it is written

    def replay(**evaluators):
        return replay_mesh_cache(model, take_path, out_dir, large_scale=mode, rest_frame=options.rest_frame,
                                 take_units=options.take_units, cache_fps=options.cache_fps,
                                 frames=_frame_slice(options.frames), head_motion=options.head_motion,
                                 chunk=options.chunk, save_large=options.save_large, extra_report={"batch": batch},
                                 **evaluators).report

    if mode == "take":
        def engine(details):
            notes = []
            evaluator = cache_evaluator(details, options.backend, options.device, options.chunk, note=notes.append)
            batch["note"] = notes[0] if notes else None
            return evaluator

        return replay(take_engine=engine)
    with _held_evaluator(model_ref, model, options) as (evaluator, batch["note"]):
        return replay(marker_evaluator=lambda m: evaluator)


def _replay_2d(take_path: str, out_dir: Path, model, model_ref: ModelRef, options: ReplayOptions, extra: dict) -> dict:
    """A 2D landmark take replayed as ``facepipe replay TAKE --camera …`` does; its replay.json report."""
    if options.camera is None:
        raise InputError("a 2D landmark take needs the camera's calibration", path=take_path,
                         hint="batch 2D takes with --camera CALIBRATION.yml (OpenCV FileStorage) or .json")
    camera = read_camera(options.camera)
    landmark_map = landmark_map_for(model, options.landmarks, take_path)
    with _held_evaluator(model_ref, model, options) as (evaluator, note):
        result, _ = replay_landmark_take(model, take_path, out_dir, camera, landmark_map, lambda m: evaluator,
                                         lift=options.lift, frames=_frame_slice(options.frames),
                                         head_motion=options.head_motion, chunk=options.chunk,
                                         save_large=options.save_large, min_confidence=options.min_confidence,
                                         extra_report={"batch": dict(extra["batch"], note=note)})
    return result.report


def _frame_slice(text: str | None):
    return parse_frame_slice(text) if text else None


def _log_attempt(out_dir: Path, worker: str) -> str:
    """Log this attempt (before it waits for the folder: a waiting attempt is seen); its id."""
    out_dir.mkdir(parents=True, exist_ok=True)
    attempt = uuid.uuid4().hex
    _append_attempts(out_dir, {"attempt": attempt, "worker": worker, "host": socket.gethostname(),
                               "pid": os.getpid(), "started": time.time()})
    return attempt


def _append_attempts(out_dir: Path, entry: dict) -> None:
    with open(out_dir / ATTEMPTS_NAME, "a", encoding="utf-8") as fh:  # one short O_APPEND write per line
        fh.write(json.dumps(entry) + "\n")


def read_attempts(out_dir: Path) -> list[dict]:
    """The attempts logged in a take's folder, in order, each with its ``error`` and
    ``traceback`` where it failed on one."""
    log = Path(out_dir) / ATTEMPTS_NAME
    attempts: dict[str, dict] = {}
    try:
        text = log.read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    for number, line in enumerate(text.splitlines()):
        try:
            entry = json.loads(line)
        except ValueError:  # a line cut short by a kill
            continue
        # lines of older logs have no id: each is an attempt of its own
        attempts.setdefault(entry.get("attempt") or f"line {number}", {}).update(entry)
    return [a for a in attempts.values() if "worker" in a]


def _remove_dead_parts(out_dir: Path) -> None:
    """Remove what killed attempts left half-written (called with the folder's lock held: no
    live attempt has files here)."""
    for part in out_dir.rglob(".*.part*"):
        part.unlink(missing_ok=True)


def describe_error(exc: BaseException) -> str:
    """An internal error in a line: its class, message and where it was raised, and the error it
    was raised while handling, if any (the original, which a failing clean-up would hide)."""
    where = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
    text = f"{exc.__class__.__name__}: {exc}" + (f" ({Path(where.filename).name}:{where.lineno})" if where else "")
    first = exc
    while first.__context__ is not None and not first.__suppress_context__:
        first = first.__context__
    if first is not exc:
        where = traceback.extract_tb(first.__traceback__)[-1] if first.__traceback__ else None
        text += (f", raised while handling {first.__class__.__name__}: {first}"
                 + (f" ({Path(where.filename).name}:{where.lineno})" if where else ""))
    return text


def format_traceback(exc: BaseException) -> str:
    return "".join(traceback.format_exception(exc))


class _ReplayWithModel(ReplayDir):
    """A take's replay folder whose exporters use the worker's model already in memory rather
    than reading the model file again for every take."""

    def __init__(self, path, model):
        super().__init__(path)
        self._model = model

    def load_model(self, override=None):
        if self._model.n_vertices != self.positions.shape[1]:
            raise InputError(f"the model has {self._model.n_vertices} vertices, the replay's positions "
                             f"{self.positions.shape[1]}", path=self.path, hint="run the batch again with --force")
        return self._model


def _export_take(out_dir: Path, name: str, fmt: str, model, model_path: str) -> dict:
    """Export a take's replay in ``fmt`` (as ``facepipe export --force`` would) with ``model``."""
    dest = export_destination(out_dir, name, fmt)
    paths, _ = export_registry.get_format(fmt).export(_ReplayWithModel(out_dir, model), dest,
                                                       ExportOptions(model_path=model_path, force=True))
    return {"dest": str(dest.relative_to(out_dir)), "files": len(paths),
            "bytes": int(sum(Path(p).stat().st_size for p in paths if Path(p).is_file()))}


def replay_take_task(job: TakeJob, model_ref: ModelRef, options: ReplayOptions, exports: tuple[str, ...] = (),
                     force: bool = False, slots_by_host: dict | None = None) -> dict:
    """One take on a worker: replay (unless its folder already holds this replay), export, stamp.

    Returns the take's :class:`TakeRecord` as a dict; a bad take (InputError, or any error of its
    own) is a ``failed`` record, not an exception, so the batch goes on and Dask does not retry
    it. Errors of the storage (OSError) are raised: Dask retries them (``retries``); each is
    logged with its traceback and reported by the attempt that ends the take.

    The attempt holds the take folder's lock throughout (another attempt at this take, of this
    batch or another, waits); an attempt of the same batch that finds the take completed by
    another keeps those outputs, ``--force`` or not."""
    t0 = time.perf_counter()
    worker = _worker_name()
    out_dir = Path(job.out_dir)
    attempt = _log_attempt(out_dir, worker)
    try:
        with take_lock(out_dir):
            return _attempt_take(job, model_ref, options, exports, force, slots_by_host, worker, t0)
    except OSError as exc:  # the storage: Dask runs the take again (retries); said in the log first
        with contextlib.suppress(OSError):
            _append_attempts(out_dir, {"attempt": attempt, "error": describe_error(exc),
                                       "traceback": format_traceback(exc)})
        raise


def _attempt_take(job: TakeJob, model_ref: ModelRef, options: ReplayOptions, exports: tuple[str, ...], force: bool,
                  slots_by_host: dict | None, worker: str, t0: float) -> dict:
    out_dir = Path(job.out_dir)
    _remove_dead_parts(out_dir)
    attempts = read_attempts(out_dir)
    record = TakeRecord(job.take, job.name, job.out_dir, "ok", worker=worker, attempts=len(attempts),
                        attempt_workers=[a.get("worker") for a in attempts], attempt_errors=_attempt_errors(attempts))
    try:
        threads = worker_threads(slots_by_host)
        parallel.set_thread_count(threads)
        reuse_freed_arrays()  # undo what the nanny's MALLOC_TRIM_THRESHOLD_ costs every chunk
        for name in POCL_THREADS_ENV:  # before this process's first OpenCL context
            os.environ.setdefault(name, str(threads))
        options_key = options.fingerprint()
        stamp = _read_stamp(out_dir)
        # completed by another attempt of this batch (one Dask gave up on, or ran twice): kept
        by_this_batch = job.batch is not None and stamp is not None and stamp.get("batch") == job.batch
        redo = force and not by_this_batch
        if redo:
            stamp = None
        if _replay_matches(stamp, job, model_ref, options_key):
            record.frames = stamp.get("frames")
            done_exports = dict(stamp.get("exports", {}))
        else:
            (out_dir / STAMP_NAME).unlink(missing_ok=True)  # the folder is incomplete until the new stamp
            model, record.model_loaded = cached_model(model_ref)
            extra = {"batch": {"worker": worker, "threads": threads, "attempt": len(attempts)}}
            report = replay_into(job.take, out_dir, model, model_ref, options, extra)
            record.frames, record.replayed, done_exports = report["frames"], True, {}
            stamp = {"take": job.take, "take_digest": job.digest, "model": model_ref.path,
                     "model_digest": model_ref.digest, "options": options_key, "frames": record.frames}
        to_export = exports if record.replayed or redo else _exports_left(stamp, job, exports)
        for fmt in to_export:
            model, loaded = cached_model(model_ref)
            record.model_loaded |= loaded
            done_exports[fmt] = _export_take(out_dir, job.name, fmt, model, model_ref.path)
        record.exports = {fmt: done_exports[fmt] for fmt in exports}
        if record.replayed or to_export or not by_this_batch:  # a finished take's stamp is left as it is
            _write_stamp(out_dir, dict(stamp, exports=done_exports, batch=job.batch, completed=time.time()))
    except OSError:
        raise
    except InputError as exc:
        record.status, record.error = "failed", str(exc)
    except Exception as exc:  # this take's own failure (a bug it exposes): reported with where it happened
        record.status = "failed"
        record.error = f"internal error {describe_error(exc)}"
        record.traceback = format_traceback(exc)
    record.seconds = time.perf_counter() - t0
    return asdict(record)


def _attempt_errors(attempts: list[dict]) -> list[dict]:
    return [{"worker": a.get("worker"), "error": a["error"], "traceback": a.get("traceback")}
            for a in attempts if a.get("error")]


def _write_stamp(out_dir: Path, stamp: dict) -> None:
    with atomic_path(out_dir / STAMP_NAME) as tmp:
        tmp.write_text(json.dumps(stamp, indent=2))


# ============================================================================= on the client


@dataclass
class BatchResult:
    records: list[TakeRecord]
    report: dict
    cluster_error: str | None = None

    @property
    def failed(self) -> list[TakeRecord]:
        return [r for r in self.records if r.status == "failed"]

    @property
    def exit_status(self) -> int:
        """0: every take done; 2: some takes failed; 1: the cluster failed."""
        return 1 if self.cluster_error else 2 if self.failed else 0


def _failed_record(job: TakeJob, error: str, tb: str | None = None) -> TakeRecord:
    attempts = read_attempts(Path(job.out_dir))
    return TakeRecord(job.take, job.name, job.out_dir, "failed", error=error, traceback=tb, attempts=len(attempts),
                      attempt_workers=[a.get("worker") for a in attempts], attempt_errors=_attempt_errors(attempts))


def _gather(client, futures: dict, on_done) -> tuple[dict[str, TakeRecord], str | None]:
    """Records of the submitted takes as they complete; a cluster error ends the wait."""
    records: dict[str, TakeRecord] = {}
    try:
        for future in as_completed(list(futures)):
            job = futures[future]
            try:
                records[job.name] = TakeRecord(**future.result())
            except KilledWorker as exc:
                records[job.name] = _failed_record(
                    job, f"workers died while running this take, {exc.last_worker and 'last ' + str(exc.last_worker.address)}"
                         f" (too much memory for a worker? see the workers' logs)")
            except OSError as exc:  # the storage, after Dask's retries: the path, the reason and the fix
                records[job.name] = _failed_record(job, describe_system_error(exc), format_traceback(exc))
            on_done(records[job.name])
    except (Exception, asyncio.CancelledError) as exc:  # the scheduler lost, futures cancelled: the cluster failed
        return records, f"{exc.__class__.__name__}: {exc}"
    return records, None


def run_batch(take_specs, model_path, out, options: ReplayOptions, exports=(), force: bool = False,
              cluster=None, retries: int = 2, progress=None, on_start=None) -> BatchResult:
    """Replay (and export) every take on a Dask cluster; write ``out/batch.json``.

    ``on_start(n_takes)`` is called once the takes are found, ``progress(record)`` as each take
    ends (skipped ones first).
    Bad input that concerns the whole batch (the model, the takes' names) raises InputError
    before any cluster starts.
    """
    cluster = cluster or ClusterSpec()
    out = Path(out).resolve()
    exports = tuple(dict.fromkeys(exports))
    for fmt in exports:
        why_not = export_registry.get_format(fmt).not_in_batch
        if why_not:
            raise InputError(f"--export {fmt}: {why_not}")
    batch_id = uuid.uuid4().hex[:8]  # task keys unique on a long-lived cluster; attempts know their batch
    jobs = plan_jobs(expand_takes(take_specs), out, batch_id)
    model = load_model(model_path)  # a bad model is the user's to fix (exit 2), before any cluster starts
    for fmt in exports:  # as is an export no replay of it can give (maps of a model without details or UVs)
        export_registry.get_format(fmt).check_model(model)
    if options.camera is not None:  # so are the 2D takes' camera and landmark map
        read_camera(options.camera)
    if options.landmarks is not None:
        landmark_map_for(model, options.landmarks, None)
    model_ref = ModelRef(str(Path(model_path).resolve()), file_digest(model_path))
    options_key = options.fingerprint()
    progress = progress or (lambda record: None)
    if on_start:
        on_start(len(jobs))
    t0 = time.perf_counter()
    records: dict[str, TakeRecord] = {}
    to_run = []
    for job in jobs:
        if job.error is not None:
            records[job.name] = _failed_record(job, job.error)
            progress(records[job.name])
            continue
        skipped = None if force else skipped_record(job, model_ref, options_key, exports)
        if skipped:
            records[job.name] = skipped
            progress(skipped)
        else:
            to_run.append(job)
    cluster_error, cluster_info = None, {"cluster": cluster.describe()}
    if to_run:
        out.mkdir(parents=True, exist_ok=True)
        for job in to_run:  # this batch's attempts only
            (Path(job.out_dir) / ATTEMPTS_NAME).unlink(missing_ok=True)
        try:
            with open_client(cluster) as client:
                slots = slots_by_host(client)
                cluster_info.update(scheduler=client.scheduler.address, workers=sum(1 for _ in client.nthreads()),
                                    slots_by_host=slots, dashboard=client.dashboard_link)
                futures = {client.submit(replay_take_task, job, model_ref, options, exports, force, slots,
                                         key=f"facepipe-take-{job.name}-{batch_id}",
                                         retries=retries, pure=False): job for job in to_run}
                ran, cluster_error = _gather(client, futures, progress)
                records.update(ran)
        except ClusterError as exc:
            cluster_error = str(exc)
    ordered = [records.get(job.name) or _failed_record(job, f"not run: the cluster failed ({cluster_error})")
               for job in jobs]
    report = _report(ordered, model_ref, options_key, exports, cluster_info, time.perf_counter() - t0, cluster_error)
    with atomic_path(out / REPORT_NAME) as tmp:
        tmp.write_text(json.dumps(report, indent=2))
    return BatchResult(ordered, report, cluster_error)


def _report(records: list[TakeRecord], model: ModelRef, options_key: dict, exports, cluster_info: dict,
            seconds: float, cluster_error: str | None) -> dict:
    count = {status: sum(r.status == status for r in records) for status in ("ok", "skipped", "failed")}
    done = [r for r in records if r.status == "ok" and r.replayed]
    frames = sum(r.frames or 0 for r in done)
    return {
        "totals": {"takes": len(records), **count, "replayed": len(done), "frames_replayed": frames,
                   "seconds": seconds, "takes_per_second": len(done) / seconds if seconds > 0 else None,
                   "frames_per_second": frames / seconds if seconds > 0 else None,
                   "retried": sum(r.attempts > 1 for r in records),
                   "task_seconds": sum(r.seconds or 0.0 for r in records)},
        "failed": [r.take for r in records if r.status == "failed"],
        "cluster_error": cluster_error,
        "model": model.path,
        "model_digest": model.digest,
        "options": options_key,
        "exports": list(exports),
        **cluster_info,
        "takes": [asdict(r) for r in records],
    }
