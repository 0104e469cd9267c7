"""Flight stacks: the layers `mapkit eval` wraps around a replanning learned method, and the runs an
ablation flies (every method under every stack asked for).

A *run* is one method under one stack. Its label names it in results.json (``methods``, each
episode's ``method``, the summary's keys): the method's name under ``full``, ``NAME@STACK`` under
any other stack, and the bare name for methods no stack changes (``straight``, ``oracle``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

from mapkit._choices import FLIGHT_STACKS, FlightStack
from mapkit.evaluation._layers import Execution
from mapkit.evaluation._methods import LEARNED_ALLOCATIONS
from mapkit.evaluation._pairs import EvalError

STACKED_METHODS = frozenset({*LEARNED_ALLOCATIONS, "untrained", "straight-keypoints", "iplanner-style"})
"""Methods whose flights a flight stack changes; the others fly once whatever ``stacks`` says."""
LABEL_SEPARATOR = "@"
_STACK_BY_NAME: dict[str, FlightStack] = {name: name for name in FLIGHT_STACKS}


def parse_stacks(text: str) -> tuple[FlightStack, ...]:
    """``--stack``'s comma list (``"full,none"``) → the stacks, in order; :class:`EvalError` names a bad
    or repeated one and the choices."""
    names = [part.strip() for part in text.split(",") if part.strip()]
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


def under_stack(execution: Execution, stack: FlightStack) -> Execution:
    """``execution`` as flown under ``stack``: ``full`` keeps every layer as configured; ``none`` keeps
    the corridor's widths and the speed profile and turns off the depth memory (with its ways out and
    the turn toward open space), the corridor's check (so the corridor flies at its
    ``unchecked_width``), the flight map's routing, following the reference and keeping the last
    plan's candidate (the paper's protocol: the network's key-points through a narrow corridor,
    replanned every interval)."""
    if stack == "full":
        return execution
    if stack == "none":
        return replace(execution, memory=None, route=None, follow=0.0, keep_choice=None,
                       corridor=replace(execution.corridor, check=False, check_memory=False))
    raise ValueError(f"unknown flight stack {stack!r}; use one of {', '.join(FLIGHT_STACKS)}")


@dataclass(frozen=True)
class Run:
    """One method flown under one flight stack."""

    method: str
    """The method's name (:data:`~mapkit.evaluation.METHODS`)."""
    stack: FlightStack | None
    """The stack it flies under; None for methods no stack changes."""

    @property
    def label(self) -> str:
        """Its name in results.json: ``method``, or ``method@stack`` under a stack other than full."""
        if self.stack is None or self.stack == "full":
            return self.method
        return f"{self.method}{LABEL_SEPARATOR}{self.stack}"


def plan_runs(methods: tuple[str, ...], stacks: tuple[FlightStack, ...]) -> list[Run]:
    """Every method under every stack (stacks inner), methods no stack changes once."""
    out: list[Run] = []
    for method in methods:
        if method in STACKED_METHODS:
            out.extend(Run(method, stack) for stack in stacks)
        else:
            out.append(Run(method, None))
    return out


def split_label(label: str) -> Run:
    """The run a results.json label names (labels without ``@`` fly the full stack or none)."""
    method, _, stack = label.partition(LABEL_SEPARATOR)
    if not stack:
        return Run(method, "full" if method in STACKED_METHODS else None)
    named = _STACK_BY_NAME.get(stack)
    if named is None:
        raise ValueError(f"label {label!r} names an unknown flight stack {stack!r}")
    return Run(method, named)
