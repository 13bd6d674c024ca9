"""``torch.compile`` helpers that every fast path shares.

The fast paths are mass-spring steps, fuzzy inference and volume rendering; the helpers are
inductor options, the "store this field" barrier, per-wrapper code objects, and the one-line
fallback warning.

Nothing here knows about springs or volumes; it sits on the ground floor next to
:mod:`torchdeform.errors` so that :mod:`torchdeform.sim`, :mod:`torchdeform.fuzzy` and
:mod:`torchdeform.volume` can all use it without importing each other.

* :func:`inductor_options`: options plus the torch thread count, which must be part of inductor's
  cache key (code generated for one thread is serial).
* :func:`realize`: an identity that inductor cannot see through, so a field is stored in memory
  once instead of being recomputed inside every loop that reads it.
* :func:`fresh`: a copy of a function with its own code object, so that dynamo keeps a cache (and a
  recompilation limit) per wrapper.
* :func:`no_autograd_cache`, :func:`skip_guards`, :func:`while_loop`, :func:`loop_cache_options`:
  the private torch switches the fast paths rely on, each with a harmless fallback where this
  torch lacks it.
* :func:`graph_cache_counts`: inductor's on-disk graph cache hits and misses so far (benchmarks
  say whether a compile was loaded or built).
* :class:`CompileFallbackWarning` and :func:`warn_fallback`: one warning line when compilation is
  unavailable and the eager code runs instead.
"""

from __future__ import annotations

import contextlib
import types
import warnings

import torch

__all__ = [
    "CompileFallbackWarning",
    "INDUCTOR_OPTIONS",
    "inductor_options",
    "realize",
    "fresh",
    "no_autograd_cache",
    "skip_guards",
    "while_loop",
    "loop_cache_options",
    "graph_cache_counts",
    "warn_fallback",
]


class CompileFallbackWarning(UserWarning):
    """``torch.compile`` is unavailable or failed; the eager step is used instead."""


_warned: set = set()


def warn_fallback(reason: str, *, what: str = "the eager step", stacklevel: int = 3) -> None:
    """Warn that compilation is unavailable and ``what`` runs instead.

    Once per kind of ``reason`` (its text before the first colon).
    """
    key = reason.split(":")[0]
    if key in _warned:
        return
    _warned.add(key)
    warnings.warn(
        f"torchdeform: torch.compile unavailable ({reason}); using {what}",
        CompileFallbackWarning,
        stacklevel=stacklevel,
    )


#: Inductor options of the packed spring step. By default inductor stores ("realises") every
#: intermediate that is read more than a few times or costs more than 30 operations; for the
#: gather loop that means one buffer per spring direction, written and read back by serial loops
#: (64^3, 26 neighbours: ~100 Msprings/s). Raising the thresholds keeps the whole force sum and
#: the update in registers, one parallel vectorised loop (~600 Msprings/s, same machine). Fields
#: that really must be stored (RK4 stages, CG directions) go through :func:`realize`.
INDUCTOR_OPTIONS = {
    "realize_opcount_threshold": 10_000,
    "realize_reads_threshold": 1_000,
    "realize_acc_reads_threshold": 1_000,
}


def inductor_options(*, options: dict | None = None, threads: int | None = None) -> dict:
    """``options`` plus a thread count (default: torch's current one) as inductor's ``cpp.threads``.

    Inductor chooses serial or OpenMP loops from the thread count at code generation, but its
    on-disk cache key does not include it: code compiled once under ``torch.set_num_threads(1)``
    would be handed, serial, to every later 2-thread run (measured: the implicit beam at 10.5 ms
    per step instead of 5.8). Naming the count makes it part of the key. The generated code runs
    on that many OpenMP threads whatever torch's setting is later (1: serial loops, no OpenMP).

    Examples:
        >>> import torch
        >>> inductor_options(options={"size_asserts": False})["cpp.threads"] == torch.get_num_threads()
        True
    """
    _register_realize_lowering()  # every torch.compile here takes its options from this
    return dict(options or {}, **{"cpp.threads": int(threads or torch.get_num_threads())})


@torch.library.custom_op("torchdeform::stored", mutates_args=())
def realize(x: torch.Tensor) -> torch.Tensor:
    """Identity that inductor cannot see through.

    Its input and output live in memory, the output contiguous in the input's axis order (so a
    permuted view is stored in that order).
    """
    return x.clone(memory_format=torch.contiguous_format)


@realize.register_fake
def _(x):
    return x.new_empty(x.shape)


_lowered: list = []


def _register_realize_lowering() -> None:
    """Lower :func:`realize` inside inductor as a stored buffer (once, on the first compile).

    The buffer is computed by the fused loop that produces it, instead of an external ``clone``
    call: each external call costs ~50-90 us of dispatch on these CPUs, several times per CG
    iteration. Without the private lowering API the op still works, as the external call.
    Registered when a compile is first asked for (:func:`inductor_options`), not on import:
    importing inductor takes ~3 s, which a run that compiles nothing should not pay.
    """
    if _lowered:
        return
    _lowered.append(True)
    try:
        from torch._inductor import lowering
    except ImportError:  # pragma: no cover
        return

    @lowering.register_lowering(torch.ops.torchdeform.stored.default, type_promotion_kind=None)
    def _lower(x):
        y = lowering.clone(x)
        y.realize()
        return y


def no_autograd_cache():
    """Compile without AOTAutograd's on-disk cache (inductor's own FX-graph cache still applies).

    Measured on the implicit beam (torch 2.13 CPU): the set-up piece loaded through that cache
    runs in 3.7 ms per call, the same inductor code compiled or loaded from the FX-graph cache in
    1.1-1.2 ms (one step: ~10 ms against ~5 ms). Without the cache a warm start costs ~10 s more.
    """
    try:
        from torch._functorch import config

        if hasattr(config, "enable_autograd_cache"):
            return config.patch(enable_autograd_cache=False)
    except ImportError:  # pragma: no cover
        pass
    return contextlib.nullcontext()


def skip_guards():
    """Run compiled code without evaluating dynamo's guards (``skip_guard_eval_unsafe``).

    For calls whose inputs match the call that compiled it; a no-op where this torch lacks the
    stance.
    """
    try:
        return torch.compiler.set_stance(skip_guard_eval_unsafe=True)
    except (AttributeError, TypeError):  # pragma: no cover
        return contextlib.nullcontext()


def fresh(fn):
    """A copy of ``fn`` with its own code object.

    Dynamo keeps its cache (and its limit of recompilations) per code object, so every wrapper
    gets its own instead of sharing one.

    Examples:
        >>> def f(x):
        ...     return x + 1
        >>> g = fresh(f)
        >>> g(1), g.__code__ is f.__code__
        (2, False)
    """
    return types.FunctionType(fn.__code__.replace(), fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)


def while_loop():
    """``torch._higher_order_ops.while_loop``, or None where this torch lacks it.

    A loop that stays one loop in the compiled graph.
    """
    try:
        from torch._higher_order_ops.while_loop import while_loop as loop
    except ImportError:  # pragma: no cover
        return None
    return loop


#: the value :func:`loop_cache_options` gives the loop's name; it is part of inductor's cache key
#: (raise it if the graphs this package builds around a loop ever need to miss old entries)
LOOP_CACHE_KEY = "torchdeform-loop-1"


def loop_cache_options() -> dict:
    """Inductor options that let its on-disk FX-graph cache keep graphs holding a ``while_loop``.

    Inductor bypasses that cache for every graph with a higher-order operator not marked
    cacheable, and torch 2.13 does not mark ``while_loop``: the compiled implicit step (its CG
    iterations in one loop) was built again in every process, 20-30 s on 2 cores. The mark
    (``unsafe_marked_cacheable_functions``, torch's opt-in) is sound for these graphs: the cache key
    pickles the whole graph module, the loop's condition and body subgraphs with their code, so
    a graph that differs only inside the loop gets another key (``tests/test_compile.py`` checks
    both a hit and that miss). Empty where this torch lacks the loop or the option.

    Examples:
        >>> opts = loop_cache_options()
        >>> opts == {} or list(opts["unsafe_marked_cacheable_functions"].values()) == [LOOP_CACHE_KEY]
        True
    """
    try:
        from torch._higher_order_ops.while_loop import while_loop_op
        from torch._inductor import config
    except ImportError:  # pragma: no cover
        return {}
    if not hasattr(config, "unsafe_marked_cacheable_functions"):  # pragma: no cover
        return {}
    return {
        "unsafe_marked_cacheable_functions": {f"{while_loop_op.__module__}.{while_loop_op.__name__}": LOOP_CACHE_KEY}
    }


def graph_cache_counts() -> tuple[int, int]:
    """``(hits, misses)`` of inductor's on-disk FX-graph cache so far in this process.

    Take the difference around a first call to tell a compile loaded from the cache (a hit) from
    one built (a miss); neither changes when the graph bypassed the cache or nothing compiled.

    Examples:
        >>> hits, misses = graph_cache_counts()
        >>> hits >= 0 and misses >= 0
        True
    """
    from torch._dynamo.utils import counters

    c = counters["inductor"]
    return int(c["fxgraph_cache_hit"]), int(c["fxgraph_cache_miss"])
