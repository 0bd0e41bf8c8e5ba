"""The only place that starts the Taichi runtime.

Importing any calendaring module has no Taichi side effects; call :func:`init_taichi`
(or let :class:`calendaring.engine.simulation.Simulation` call it) before building pools.

See also: :mod:`calendaring.engine.simulation`, :mod:`calendaring.engine.laws.eepa` (its
host-side :func:`~calendaring.engine.laws.eepa.evaluate` starts the runtime too).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import taichi as ti

from calendaring.core.config import available_cores
from calendaring.core.errors import ConfigError

_STATE: dict = {"settings": None, "optimise": True}

OFFLINE_CACHE_BYTES = 1 << 30
"""Size of the offline kernel cache above which Taichi deletes its least recently used
quarter [bytes]."""


@dataclass(frozen=True)
class BackendInfo:
    """What :func:`init_taichi` started."""

    arch: str  # "cpu" or "cuda"
    precision: str  # "f64"
    threads: int  # CPU threads (0 = Taichi default)
    seed: int
    cache_dir: str


def set_kernel_optimisation(full: bool) -> None:
    """Choose, for the whole process, how much Taichi optimises the kernels it compiles.

    ``full=True`` (the default, and what every run, sweep and benchmark uses): Taichi's
    advanced IR optimisations. ``full=False`` turns them off: a kernel compiles about 3 x
    faster (the multi-step launch of a small bed: 9.3 -> 3.2 s on one x86 core) and runs
    about 10 % slower (the benchmark bed: 544 -> 494 steps/s on one thread). The results
    are those of the same source; the test suite uses it in its own processes (the runs
    it starts as subprocesses keep the full optimisation). The kernels of each setting
    have their own keys in the offline cache. Takes effect at the next
    :func:`init_taichi`; raises RuntimeError while the runtime is up with the other one.
    """
    full = bool(full)
    if _STATE["settings"] is not None and _STATE["optimise"] != full:
        raise RuntimeError("Taichi is running with the other kernel optimisation; call "
                           "calendaring.engine.backend.reset_taichi() first")
    _STATE["optimise"] = full


def default_cache_dir() -> Path:
    """Offline kernel cache directory (``$CALENDARING_KERNEL_CACHE`` or ~/.cache)."""
    env = os.environ.get("CALENDARING_KERNEL_CACHE")
    if env:
        return Path(env)
    return Path.home() / ".cache" / "calendaring" / "taichi"


def init_taichi(
    arch: str = "cpu",
    precision: str = "f64",
    seed: int = 0,
    threads: int = 0,
    offline_cache: bool = True,
    cache_dir: str | Path | None = None,
    debug: bool = False,
) -> BackendInfo:
    """Start Taichi once per process; later calls with the same settings are no-ops.

    Args:
        arch: "cpu", "cuda" or "auto" (CUDA when available, else CPU).
        precision: "f64" (default float type of every kernel).
        seed: Taichi's random seed (``ti.random``).
        threads: CPU threads, 0 = all cores.
        offline_cache: keep compiled kernels on disk between processes.
        cache_dir: where the offline cache lives (default :func:`default_cache_dir`).
        debug: Taichi debug mode (bounds checks; slow).

    Raises:
        ConfigError: unknown arch or precision, or CUDA requested but unavailable.
        RuntimeError: Taichi already started with different settings (fields allocated
            under the old runtime would be invalidated).
    """
    if arch not in ("cpu", "cuda", "auto"):
        raise ConfigError("numerics.arch", arch, "cpu, cuda or auto")
    if precision != "f64":
        raise ConfigError("numerics.precision", precision, "f64")
    cache = str(cache_dir or default_cache_dir())
    key = (arch, precision, seed, threads, offline_cache, cache, debug, _STATE["optimise"])
    if _STATE["settings"] is not None:
        if _STATE["settings"][0] == key:
            return _STATE["settings"][1]
        raise RuntimeError(
            f"Taichi already initialised with {_STATE['settings'][0]}; requested {key}. "
            "Call calendaring.engine.backend.reset_taichi() first (this invalidates every pool)."
        )
    # "auto" asks for CUDA, which Taichi replaces by the CPU when no CUDA device answers
    # (ti.gpu would also probe Vulkan and OpenGL, which can crash a headless machine)
    ti_arch = ti.cuda if arch in ("cuda", "auto") else ti.cpu
    kwargs = dict(
        arch=ti_arch,
        default_fp=ti.f64,
        default_ip=ti.i32,
        random_seed=seed,
        offline_cache=offline_cache,
        offline_cache_file_path=cache,
        # Taichi deletes the least recently used quarter of the cache once it holds more
        # than 100 MB (its default); the test suite alone compiles about 105 MB of kernels,
        # so each full run evicted what the next one needed
        offline_cache_max_size_of_files=OFFLINE_CACHE_BYTES,
        debug=debug,
        log_level=ti.WARN,
        # IEEE arithmetic: with fast math LLVM may reorder sums differently in two kernels
        # that inline the same function (the one-launch-per-step and multi-step paths
        # then drift apart in the last bits) and may drop NaN tests (the guards); it
        # measured no faster here
        fast_math=False,
        advanced_optimization=_STATE["optimise"],
    )
    if arch != "cuda":  # the CPU's thread pool ("auto" may fall back to the CPU)
        kwargs["cpu_max_num_threads"] = cpu_pool_threads(threads)
    ti.init(**kwargs)
    memoise_source_positions()
    actual = "cuda" if ti.lang.impl.current_cfg().arch == ti.cuda else "cpu"
    if arch == "cuda" and actual != "cuda":
        ti.reset()
        raise ConfigError("numerics.arch", arch, "cpu or auto: no CUDA device is available")
    info = BackendInfo(arch=actual, precision=precision, threads=threads, seed=seed,
                       cache_dir=cache)
    _STATE["settings"] = (key, info)
    return info


def memoise_source_positions() -> bool:
    """Make Taichi's compiler front end remember the source-position text of AST nodes.

    Taichi 1.7 rebuilds every kernel of every new :class:`~calendaring.engine.simulation.
    Simulation` from its Python syntax tree (the kernels are bound to that instance's
    fields) before it looks in the offline cache, and for each node it formats a message
    with the file, line and a caret under the code, for compile errors and debug info
    (``ASTTransformerContext.get_pos_info``). A ``ti.func`` inlined in many kernels formats
    the same message again each time; that formatting took about a third of the front
    end's time. The message depends only on where the node sits in its file, so this
    keeps one copy per position: the text handed to Taichi, and so the kernels and the
    cache keys, are unchanged. Returns False (and changes nothing) on a Taichi without that
    method.
    """
    try:
        from taichi.lang.ast.ast_transformer_utils import ASTTransformerContext
    except ImportError:
        return False
    original = getattr(ASTTransformerContext, "get_pos_info", None)
    if original is None:
        return False
    if getattr(original, "memoised", False):
        return True
    memo: dict[tuple, str] = {}

    def get_pos_info(ctx, node):
        body = getattr(node, "body", None)
        first = body[0].lineno if isinstance(body, list) and body else None
        key = (ctx.file, ctx.lineno_offset, ctx.func.func.__name__, ctx.indent, len(ctx.src),
               type(node).__name__, node.lineno, node.end_lineno, node.col_offset,
               node.end_col_offset, first)
        text = memo.get(key)
        if text is None:
            text = memo[key] = original(ctx, node)
        return text

    get_pos_info.memoised = True
    get_pos_info.original = original
    get_pos_info.__doc__ = original.__doc__
    ASTTransformerContext.get_pos_info = get_pos_info
    return True


def cpu_pool_threads(threads: int) -> int:
    """Taichi CPU worker threads for ``threads`` cores (0 = every core this process may use,
    :func:`available_cores`): one per core.

    The steps run as multi-step launches whose workers spin at barriers
    (``calendaring.engine.forces.Kernels.burst``); with more pool threads than cores two workers
    can share a core, and a barrier then waits for the scheduler's time slice (measured on
    a 2-core VM, 100-step launches of a 2-particle bed: 1.3 ms with 2 pool threads, 12 ms
    with 4). (One launch per step, the path before multi-step launches, ran faster with two
    per core: a worker still asleep when a sub-millisecond loop starts leaves its core idle.)
    """
    return threads or available_cores()


def serial_loops(threads: int) -> bool:
    """Whether the per-step loops run serialised: on the CPU backend with one thread only
    (a parallel loop's dispatch costs more than a small bed's work there). On CUDA every
    loop stays parallel whatever ``numerics.threads`` says."""
    info = current_backend()
    return int(threads) == 1 and (info is None or info.arch == "cpu")


def burst_workers(threads: int) -> int:
    """Worker threads of a multi-step launch (``calendaring.engine.forces.Kernels.burst``): one per
    core asked for (``threads``, 0 = every core), 1 for a serial run; 0 on CUDA, where a
    launch cannot hold its blocks at a barrier and every step is its own launch."""
    info = current_backend()
    if info is not None and info.arch != "cpu":
        return 0
    return max(1, cpu_pool_threads(int(threads)))


def current_backend() -> BackendInfo | None:
    """The running backend, or None before :func:`init_taichi`."""
    return _STATE["settings"][1] if _STATE["settings"] else None


def reset_taichi() -> None:
    """Shut the runtime down (every field and pool becomes invalid)."""
    if _STATE["settings"] is not None:
        ti.reset()
        _STATE["settings"] = None
