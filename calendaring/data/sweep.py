"""Parameter sweeps: many calendering runs over a design, as tasks on Dask distributed.

    calendaring sweep --design lhs --n 280 --preset sweep --out RUNS/
    calendaring sweep --design lhs --n 3 --replicates 5 --role replicate --out RUNS/
    calendaring sweep --design lhs --n 10 --design-seed 1 --role holdout --out RUNS/
    calendaring sweep ... --scheduler tcp://host:8786          # an existing cluster

Layout of ``RUNS/``::

    manifest.json               one entry per run: status, attempts, wall time, error text
    designs/<label>.csv         the design rows (physical units), its report and heatmap
    packings/<key>.csv          one settled bed per (base configuration, seed)
    runs/<run_id>.h5            one run file per run; run_id = <role>-<label>-<index>-s<seed>-
                                <hash>, the hash over the run's full configuration
    digests/<run_id>.h5         the run's digest (calendaring.data.digest, ~30 kB): what a dataset
                                needs; a run with a complete digest counts as finished
                                even without its run file, so a sweep's digests and
                                manifest, kept in the repository, resume it on a new machine
    logs/<run_id>.log           the run's output (progress lines, diagnostics)

Every run is a task on a Dask cluster (a ``LocalCluster`` of ``--workers`` by default) that
starts ``python -m calendaring.cli run`` in a subprocess, so a crash, an instability or a
leak of one run cannot take the sweep down. Runs of one seed share one settled bed, built
once by a task they depend on (``calendaring pack``); the bed does not depend on the breakage
parameters (the build stages are breakage-free).

Resuming: rerunning the same command skips runs whose file exists and reads back, and
retries failed runs up to ``--max-attempts``. The manifest is rewritten atomically after every
finished task, and a run in flight keeps its own checkpoint (``output.checkpoint_interval``),
which the retry resumes from; a crash or SIGKILL of the sweep loses at most the work since
those checkpoints. Children die with the sweep (``PR_SET_PDEATHSIG``), and a lock file stops
two sweeps from working on one folder at once.

See also: :mod:`calendaring.data.design` (the designs), :mod:`calendaring.data.digest`
(what marks a run finished), :mod:`calendaring.process.run` (the staged run of each task).
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from calendaring.core.config import (
    SimConfig,
    available_cores,
    config_hash_excluding,
    config_json,
    format_override,
    load_config,
    load_preset,
    with_overrides,
)
from calendaring.core.errors import ConfigError
from calendaring.core.fileio import write_json
from calendaring.data.design import (
    DESIGNS,
    design_report,
    make_design,
    plot_correlation,
    write_design_csv,
)
from calendaring.data.params import PAPER_SPACE, ParameterSpace
from calendaring.process.runfile import RunRecord, previous_checkpoint

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "calendaring-sweep"
ROLES = ("train", "replicate", "holdout", "refine")  # refine: added by `inverse refine`
STATUSES = ("pending", "running", "done", "failed")


@dataclass
class RunEntry:
    """One run of a sweep, as stored in the manifest."""

    run_id: str
    role: str
    design: str  # design label (e.g. lhs-n280-d0)
    index: int  # row of the design
    seed: int
    group: str  # replicate group ("" if none): same parameters, several seeds
    params: dict[str, float]
    source: str  # "preset:<name>" or the config TOML path
    overrides: dict[str, object]
    packing: str  # packing key (file packings/<key>.csv)
    file: str  # runs/<run_id>.h5
    status: str = "pending"
    attempts: int = 0
    wall_time: float | None = None  # s, of the last attempt
    error: str = ""
    finished: str = ""
    history: list = field(default_factory=list)  # [(status, wall_time, error)] per attempt


# ---------------------------------------------------------------------- planning
def base_config(source: str, overrides: dict) -> SimConfig:
    """The configuration every run of the sweep starts from."""
    if source.startswith("preset:"):
        cfg = load_preset(source.split(":", 1)[1])
    else:
        cfg = load_config(Path(source))
    return with_overrides(cfg, overrides) if overrides else cfg


def run_config(base: SimConfig, params: dict[str, float], seed: int) -> SimConfig:
    o = {f"breakage.{k}": float(v) for k, v in params.items()}
    o["numerics.seed"] = int(seed)
    o["breakage.enabled"] = True
    return with_overrides(base, o).check_run()


def packing_key(cfg: SimConfig) -> str:
    """Hash of what the settled bed depends on: the configuration without the breakage,
    protocol and output sections (seed included) and without ``numerics.resort_fraction``
    (a bed is settled before anything breaks; left out, the keys of sweeps made before the
    key existed stay the same)."""
    return config_hash_excluding(cfg, ("breakage", "protocol", "output",
                                       "numerics.resort_fraction"))[:16]


def plan(source: str, overrides: dict, design: str, n: int, design_seed: int, seed: int,
         replicates: int, role: str, space: ParameterSpace = PAPER_SPACE,
         seed_per_row: bool = False, beds: int = 0
         ) -> tuple[np.ndarray, str, list[RunEntry]]:
    """The design rows, their label and the run entries of one sweep invocation. The runs
    of a row take seeds ``seed``, ``seed + 1``, ... (one per replicate); with
    ``seed_per_row`` each row has its own: ``seed + row x replicates + replicate`` (every
    run on a bed of its own); with ``beds = K`` the rows take turns over K beds:
    ``seed + (row mod K) x replicates + replicate`` (a model trained on them learns the
    mean over K beds, not one bed's deviation, for K settlings only)."""
    if role not in ROLES:
        raise ConfigError("--role", role, f"one of {ROLES}")
    if beds < 0 or (beds and seed_per_row):
        raise ConfigError("--beds", beds, "an integer >= 1, and not with --seed-per-row")
    if replicates < 1:
        raise ConfigError("--replicates", replicates, ">= 1")
    if design in DESIGNS and design not in ("reference",) and n < 1:
        raise ConfigError("--n", n, ">= 1")
    x = make_design(design, n, design_seed, space)
    label = (Path(design).stem if design.endswith(".csv") else
             f"{design}-n{len(x)}-d{design_seed}")
    base = base_config(source, overrides)
    entries = []
    for i, row in enumerate(x):
        params = space.as_dict(row)
        for r in range(replicates):
            turn = i if seed_per_row else (i % beds if beds else 0)
            s = seed + turn * replicates + r
            cfg = run_config(base, params, s)
            h = hashlib.sha256(config_json(cfg).encode()).hexdigest()[:10]
            run_id = f"{role}-{label}-{i:04d}-s{s}-{h}"
            entries.append(RunEntry(
                run_id=run_id, role=role, design=label, index=i, seed=s,
                group=f"{label}-{i:04d}" if replicates > 1 else "", params=params,
                source=source, overrides=dict(overrides), packing=packing_key(cfg),
                file=f"runs/{run_id}.h5"))
    return x, label, entries


# ---------------------------------------------------------------------- manifest
def read_manifest(folder: Path) -> dict[str, RunEntry]:
    path = Path(folder) / MANIFEST
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
        if data.get("format") != MANIFEST_FORMAT:
            raise ValueError(f"format {data.get('format')!r}")
        return {k: RunEntry(**v) for k, v in data["runs"].items()}
    except Exception as err:
        raise ConfigError("--out", str(folder), f"a sweep folder with a readable {MANIFEST} "
                          f"({path} is unreadable: {err})") from None


def write_manifest(folder: Path, runs: dict[str, RunEntry]) -> Path:
    counts = {s: sum(1 for e in runs.values() if e.status == s) for s in STATUSES}
    data = {"format": MANIFEST_FORMAT, "updated": _now(), "counts": counts,
            "runs": {k: asdict(v) for k, v in sorted(runs.items())}}
    return write_json(Path(folder) / MANIFEST, data)


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def finished(folder: Path, file: str) -> bool:
    """Is the run ``file`` (relative to the sweep ``folder``) finished: a complete run file,
    or, without one, a complete digest (``digests/<run>.h5``, e.g. restored from the
    repository on a fresh machine)?"""
    from calendaring.data.digest import digest_ok, digest_path

    path = Path(folder) / file
    return run_file_ok(path)[0] or digest_ok(digest_path(folder, path.stem))[0]


def write_run_digest(folder: Path, file: str, rec: RunRecord | None = None) -> Path:
    """Write the digest of the finished run ``file`` of the sweep ``folder`` (from ``rec``,
    its record, if already read)."""
    from calendaring.data.digest import digest_path, write_digest
    from calendaring.process.runfile import read_run

    path = Path(folder) / file
    return write_digest(digest_path(folder, path.stem), rec or read_run(path))


def read_complete_run(path: Path) -> tuple[RunRecord | None, str]:
    """The record of ``path`` if it reads back as a complete run file, else (None, why)."""
    from calendaring.process.runfile import RunFileError, incomplete_stroke, read_run

    if not Path(path).exists():
        return None, "no run file"
    try:
        rec = read_run(path)
    except RunFileError as err:
        return None, str(err)
    why = incomplete_stroke(rec.info.get("final_depth", 0.0), rec.stroke,
                            rec.config.protocol.target_pressure)
    return (None, why) if why else (rec, "")


def run_file_ok(path: Path) -> tuple[bool, str]:
    """Does ``path`` exist and read back as a complete run file?"""
    rec, why = read_complete_run(path)
    return rec is not None, why


# ---------------------------------------------------------------------- tasks (on workers)
def _pdeathsig() -> None:  # runs in the child before exec: die with the parent
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)


def _tail(path: Path, n: int = 15) -> str:
    try:
        lines = Path(path).read_text(errors="replace").splitlines()
    except OSError:
        return ""
    return "\n".join(lines[-n:])


def _subprocess(args: list[str], log: Path, timeout: float | None) -> tuple[int, float]:
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "a") as fh:
        fh.write(f"# {_now()} {' '.join(args)}\n")
        fh.flush()
        try:
            rc = subprocess.run([sys.executable, "-m", "calendaring.cli", *args], stdout=fh,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                timeout=timeout, preexec_fn=_pdeathsig).returncode
        except subprocess.TimeoutExpired:
            rc = -9
            fh.write(f"\nsweep: killed after the {timeout} s timeout\n")
    return rc, time.perf_counter() - t0


def pack_task(folder: str, source: str, overrides: dict, seed: int, key: str,
              threads: int) -> str:
    """Settle the bed for ``key`` unless its packing exists; returns the packing path."""
    folder = Path(folder)
    out = folder / "packings" / f"{key}.csv"
    if out.exists():
        return str(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    args = ["pack", *_source_args(source, overrides), "--seed", str(seed), "--threads",
            str(threads), "--quiet", "--out", str(out)]
    rc, _ = _subprocess(args, folder / "logs" / f"pack-{key}.log", None)
    if rc != 0 or not out.exists():
        raise RuntimeError(f"settling the bed {key} failed (exit {rc}):\n"
                           + _tail(folder / "logs" / f"pack-{key}.log"))
    return str(out)


def run_task(folder: str, entry: dict, packing: str, threads: int,
             timeout: float | None) -> dict:
    """One calendering run in a subprocess; returns status, wall time and error text."""
    folder = Path(folder)
    out = folder / entry["file"]
    if finished(folder, entry["file"]):
        return {"status": "done", "wall_time": 0.0, "error": "", "reused": True}
    ckpt = out.with_name(out.name + ".ckpt")
    prev = previous_checkpoint(ckpt)
    sets = [format_override(f"breakage.{k}", float(v)) for k, v in entry["params"].items()]
    sets += [format_override("breakage.enabled", True),
             format_override("electrode.packing", packing)]
    args = ["run", *_source_args(entry["source"], entry["overrides"])]
    for s in sets:
        args += ["--set", s]
    args += ["--seed", str(entry["seed"]), "--threads", str(threads), "--quiet", "--overwrite",
             "--out", str(out)]
    if ckpt.exists() or prev.exists():  # the run refuses a bad one and starts afresh
        args += ["--resume", "--restart-if-unusable"]
    log = folder / "logs" / f"{entry['run_id']}.log"
    rc, wall = _subprocess(args, log, timeout)
    rec, why = read_complete_run(out)
    if rc == 0 and rec is not None:
        write_run_digest(folder, entry["file"], rec)
        return {"status": "done", "wall_time": wall, "error": "", "reused": False}
    kind = {3: "unstable (guard stop)", 2: "bad input or file-system error",
            1: "internal error (a bug)",
            -9: "killed (SIGKILL: the timeout or from outside)"}.get(rc, f"exit {rc}")
    return {"status": "failed", "wall_time": wall, "reused": False,
            "error": f"{kind}: {_tail(log) or why}"}


def _source_args(source: str, overrides: dict) -> list[str]:
    args = (["--preset", source.split(":", 1)[1]] if source.startswith("preset:")
            else [source])
    for k, v in overrides.items():
        args += ["--set", format_override(k, v)]
    return args


# ---------------------------------------------------------------------- driver
@contextlib.contextmanager
def _folder_lock(folder: Path):
    import fcntl

    folder.mkdir(parents=True, exist_ok=True)
    fh = open(folder / ".sweep.lock", "w")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fh.close()
        raise ConfigError("--out", str(folder), "a folder no other sweep is working on "
                          "(another sweep holds its lock)") from None
    try:
        yield
    finally:
        fcntl.flock(fh, fcntl.LOCK_UN)
        fh.close()


@dataclass
class SweepOptions:
    source: str  # "preset:<name>" or a config TOML path
    out: Path
    design: str = "lhs"
    n: int = 1
    seed: int = 0
    design_seed: int | None = None
    replicates: int = 1
    role: str = "train"
    overrides: dict = field(default_factory=dict)
    workers: int = 0  # 0 = one per core
    threads_per_run: int = 1
    scheduler: str | None = None  # address of an existing Dask scheduler
    max_attempts: int = 2
    timeout: float | None = None  # s per run attempt
    gpu: bool = False  # ask each task for one "GPU" worker resource
    progress: bool = True
    seed_per_row: bool = False  # each design row its own seed (bed), see plan()
    beds: int = 0  # rows take turns over this many seeds (beds), see plan(); 0: off


def sweep(opt: SweepOptions, task=None, pack=None) -> dict[str, RunEntry]:
    """Plan (or extend) the sweep in ``opt.out`` and run what is not done yet.

    ``task`` replaces :func:`run_task` and ``pack`` :func:`pack_task` (same signatures;
    tests inject failures and stand-in runs with them). Returns the manifest entries of the
    whole folder.
    """
    from calendaring.process.run import Progress

    out = Path(opt.out)
    dseed = opt.seed if opt.design_seed is None else opt.design_seed
    x, label, planned = plan(opt.source, opt.overrides, opt.design, opt.n, dseed, opt.seed,
                             opt.replicates, opt.role, seed_per_row=opt.seed_per_row,
                             beds=opt.beds)
    task = task or run_task
    with _folder_lock(out):
        for sub in ("designs", "packings", "runs", "digests", "logs"):
            (out / sub).mkdir(parents=True, exist_ok=True)
        write_design_csv(out / "designs" / f"{label}.csv", x)
        rep = design_report(x)
        write_json(out / "designs" / f"{label}.json", rep)
        if rep["pearson"] is not None:
            plot_correlation(rep, out / "designs" / f"{label}_correlation.png")
        runs = read_manifest(out)
        for e in planned:
            runs.setdefault(e.run_id, e)
        todo = []
        for e in planned:
            cur = runs[e.run_id]
            if finished(out, cur.file):
                cur.status = "done"
            elif cur.status == "failed" and cur.attempts >= opt.max_attempts:
                continue
            else:
                cur.status = "pending"
                todo.append(cur)
        write_manifest(out, runs)
        n_done = sum(1 for e in planned if runs[e.run_id].status == "done")
        _log(f"sweep {label} ({opt.role}, x{opt.replicates}): {len(planned)} runs, {n_done} "
             f"done, {len(todo)} to run, "
             f"{len(planned) - n_done - len(todo)} failed {opt.max_attempts} times; "
             f"design max |r| = {rep['max_abs_r'] if rep['max_abs_r'] is not None else 'n/a'}")
        if todo:
            _execute(opt, out, runs, todo, task, pack or pack_task, Progress)
        write_manifest(out, runs)
    return runs


def _log(msg: str) -> None:
    print(f"[sweep] {msg}", file=sys.stderr, flush=True)


def _execute(opt: SweepOptions, out: Path, runs: dict[str, RunEntry], todo: list[RunEntry],
             task, pack, Progress) -> None:
    from dask.distributed import Client, LocalCluster, as_completed

    if opt.scheduler:
        client = Client(opt.scheduler)
        cluster = None
    else:
        workers = opt.workers or max(1, available_cores() // max(1, opt.threads_per_run))
        # Tasks only wait on subprocesses, so thread workers in this process suffice
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=False,
                               dashboard_address=None)
        client = Client(cluster)
    resources = {"GPU": 1} if opt.gpu else None
    try:
        packs = {}
        for e in todo:
            if e.packing not in packs:
                packs[e.packing] = client.submit(
                    pack, str(out), e.source, e.overrides, e.seed, e.packing,
                    opt.threads_per_run, key=f"pack-{e.packing}", pure=False,
                    resources=resources)
        futures = {}

        def submit(e: RunEntry):
            f = client.submit(task, str(out), asdict(e), packs[e.packing], opt.threads_per_run,
                              opt.timeout, key=f"run-{e.run_id}-a{e.attempts + 1}",
                              pure=False, resources=resources)
            futures[f] = e.run_id
            e.status = "running"
            return f

        pending = as_completed([submit(e) for e in todo])
        write_manifest(out, runs)
        bar = Progress("sweep", len(todo), opt.progress, every=0.0, unit="runs")
        bar.update(0)
        done = 0
        for f in pending:
            e = runs[futures[f]]
            try:
                res = f.result()
            except Exception as err:  # the packing or the task itself failed
                res = {"status": "failed", "wall_time": None, "error": f"{type(err).__name__}: "
                       f"{err}", "reused": False}
            if not res.get("reused"):
                e.attempts += 1
            e.status, e.wall_time, e.error = res["status"], res["wall_time"], res["error"]
            e.finished = _now()
            err = e.error if len(e.error) <= 500 else f"{e.error[:200]} [...] {e.error[-300:]}"
            e.history.append([e.status, e.wall_time, err])  # the kind of failure, the tail
            write_manifest(out, runs)
            done += 1
            wall = f"{e.wall_time:.0f} s" if e.wall_time is not None else "-"
            bar.update(done, f"{e.run_id} {e.status} ({wall})", force=True)
            if e.status == "failed":
                _log(f"{e.run_id} failed (attempt {e.attempts}): "
                     f"{e.error.splitlines()[0] if e.error else ''}")
                # a killed or crashed run resumes from its checkpoint at once; a guard stop
                # is deterministic, so it waits for a later invocation (if any attempts left)
                if e.attempts < opt.max_attempts and not e.error.startswith("unstable"):
                    _log(f"{e.run_id}: retrying (attempt {e.attempts + 1} of "
                         f"{opt.max_attempts})")
                    pending.add(submit(e))
                    done -= 1
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def summary(runs: dict[str, RunEntry]) -> dict:
    """Counts and wall times of a manifest (for the closing log line and notes)."""
    walls = [e.wall_time for e in runs.values() if e.status == "done" and e.wall_time]
    return {"runs": len(runs),
            **{s: sum(1 for e in runs.values() if e.status == s) for s in STATUSES},
            "wall_time_mean": float(np.mean(walls)) if walls else None,
            "wall_time_total": float(np.sum(walls)) if walls else None}


__all__ = [
    "MANIFEST",
    "ROLES",
    "RunEntry",
    "SweepOptions",
    "finished",
    "pack_task",
    "plan",
    "read_complete_run",
    "read_manifest",
    "run_file_ok",
    "run_task",
    "summary",
    "sweep",
    "write_manifest",
    "write_run_digest",
]
