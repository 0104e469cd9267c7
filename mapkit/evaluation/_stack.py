"""The runs an ablation flies: every method under every flight stack asked for
(:func:`mapkit.flight.under_stack`), labelled in results.json ``NAME`` under ``full`` (and for methods
no stack changes), ``NAME@STACK`` otherwise, and ``untrained#SEED[@STACK]`` per initial weights when
``untrained`` flies several."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

from mapkit._choices import FLIGHT_STACKS, FlightStack
from mapkit.evaluation._methods import LEARNED_ALLOCATIONS
from mapkit.evaluation._pairs import EvalError

STACKED_METHODS = frozenset({*LEARNED_ALLOCATIONS, "untrained", "straight-keypoints", "iplanner-style"})
"""Methods whose flights a flight stack changes; the others fly once whatever ``stacks`` says."""
LABEL_SEPARATOR = "@"
INIT_SEPARATOR = "#"
UNTRAINED_SEEDS = (0, 1, 2, 3)
"""The initial weights ``untrained`` flies, each every pair as ``untrained#SEED``; the ablation pools
them (one seed alone is a lottery)."""
_STACK_BY_NAME: dict[str, FlightStack] = {name: name for name in FLIGHT_STACKS}


def parse_stacks(text: str) -> tuple[FlightStack, ...]:
    """``--stack``'s comma list (``"full,none"``) → the stacks, in order (:func:`check_stacks`)."""
    return check_stacks([part.strip() for part in text.split(",") if part.strip()])


def check_stacks(names: Sequence[str]) -> tuple[FlightStack, ...]:
    """The stacks ``names``; :class:`EvalError` names a bad or repeated one and the choices."""
    out: list[FlightStack] = []
    for name in names:
        stack = _STACK_BY_NAME.get(name)
        if stack is None or stack in out:
            what = "unknown flight stack" if stack is None else "flight stack given twice:"
            raise EvalError(f"--stack: {what} {name!r}; use a comma list of {', '.join(FLIGHT_STACKS)}")
        out.append(stack)
    if not out:
        raise EvalError(f"--stack is empty; use a comma list of {', '.join(FLIGHT_STACKS)}")
    return tuple(out)


@dataclass(frozen=True)
class Run:
    """One method flown under one flight stack."""

    method: str
    """The method's name (:data:`~mapkit.evaluation.METHODS`)."""
    stack: FlightStack | None
    """The stack it flies under; None for methods no stack changes."""
    init_seed: int | None = None
    """The seed of ``untrained``'s initial weights when an evaluation flies several; None otherwise."""

    @property
    def label(self) -> str:
        """Its name in results.json: ``method`` (``method#seed``), with ``@stack`` under a stack other
        than full."""
        name = self.method if self.init_seed is None else f"{self.method}{INIT_SEPARATOR}{self.init_seed}"
        if self.stack is None or self.stack == "full":
            return name
        return f"{name}{LABEL_SEPARATOR}{self.stack}"

    @property
    def pooled(self) -> str:
        """The label its initial weights are pooled under (its own label when it has no ``init_seed``)."""
        return replace(self, init_seed=None).label


def plan_runs(methods: tuple[str, ...], stacks: tuple[FlightStack, ...], untrained_seeds: tuple[int, ...] = (0,)) -> list[Run]:
    """Every method under every stack (stacks inner, then ``untrained``'s seeds when there are several),
    methods no stack changes once."""
    out: list[Run] = []
    for method in methods:
        if method not in STACKED_METHODS:
            out.append(Run(method, None))
            continue
        seeds: tuple[int | None, ...] = untrained_seeds if method == "untrained" and len(untrained_seeds) > 1 else (None,)
        out.extend(Run(method, stack, seed) for stack in stacks for seed in seeds)
    return out


def split_label(label: str) -> Run:
    """The run a results.json label names (labels without ``@`` fly the full stack or none)."""
    name, _, stack = label.partition(LABEL_SEPARATOR)
    method, separator, seed = name.partition(INIT_SEPARATOR)
    if separator and not seed.isdigit():
        raise ValueError(f"label {label!r} names an initial-weights seed {seed!r} that is not a whole number")
    init_seed = int(seed) if separator else None
    if not stack:
        return Run(method, "full" if method in STACKED_METHODS else None, init_seed)
    named = _STACK_BY_NAME.get(stack)
    if named is None:
        raise ValueError(f"label {label!r} names an unknown flight stack {stack!r}")
    return Run(method, named, init_seed)
