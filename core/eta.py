"""How long a running job has left, from rates measured on this job and on the service's earlier jobs.

A job's record keeps its ``work``: the number of input frames, each finished stage's seconds and unit count
(frames, pairs, blocks: what its progress reports count) and the running stage's start, share done and units
done. From it:

- **the running stage** goes at its own measured rate (share done per second: frames/s, pairs/s, blocks/s as
  its reports count them), blended with its expected time while little of it is done (weight: the share done);
- **the stages to come** take their expected time: seconds per input frame measured for that stage on the
  service's recent jobs of the same pipeline (``history``), times this job's frames, times how much slower or
  faster this job has run so far than those jobs predicted (``pace``, damped toward 1 early on). A stage
  without history takes its pipeline weight (its planned share of the job) at the pace of the finished stages.

Nothing here reads a clock or a database: callers pass the elapsed seconds and the history.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

# "frame 4/12", "pair 3/20", "block 7/30", "load step 2/5"; the unit is the word(s) before the count
_COUNT = re.compile(r"([A-Za-z][A-Za-z ]*?)\s+(\d+)\s*/\s*(\d+)")
BASES = ("measured", "history", "weights", "done")  # what a stage's time left comes from (core.labels names each)
PRIOR_WEIGHT = 0.25  # how many "whole jobs" of evidence the history's pace counts for before this job's own


@dataclass(frozen=True)
class UnitCount:
    unit: str  # e.g. "frame"
    done: int
    total: int


def parse_count(detail: str) -> UnitCount | None:
    """The unit and count of a progress detail (``"frame 4/12"`` -> frame, 4, 12); None when it has none."""
    match = _COUNT.search(detail or "")
    if match is None or int(match[3]) <= 0:
        return None
    return UnitCount(match[1].strip().lower(), int(match[2]), int(match[3]))


@dataclass
class StageEta:
    seconds_left: float
    basis: str  # "measured": its own rate; "history": earlier jobs; "weights": the pipeline's plan; "done"
    unit: str | None = None
    units_per_second: float | None = None  # measured on this stage, in its unit


@dataclass
class Eta:
    seconds_left: float  # the whole job
    stage_seconds_left: float  # the running stage
    stages: dict[str, StageEta] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "seconds_left": round(self.seconds_left, 1),
            "stage_seconds_left": round(self.stage_seconds_left, 1),
            "stages": {
                name: {
                    "seconds_left": round(s.seconds_left, 1),
                    "basis": s.basis,
                    "unit": s.unit,
                    "units_per_second": None if s.units_per_second is None else round(s.units_per_second, 3),
                }
                for name, s in self.stages.items()
            },
        }


def estimate(
    stages: Sequence[tuple[str, float]],
    frames: int,
    finished: Mapping[str, float],
    current: str | None,
    fraction: float,
    elapsed: float,
    history: Mapping[str, float] | None = None,
    count: UnitCount | None = None,
) -> Eta | None:
    """The time left of a job whose pipeline runs ``stages`` (name, weight) in order over ``frames`` inputs.

    ``finished``: seconds of the stages done; ``current``: the running stage (None: waiting for the next one),
    ``fraction`` of it done after ``elapsed`` seconds, its last ``count``; ``history``: seconds per input frame of
    each stage on earlier jobs. None while nothing has been measured and there is no history to go by.
    """
    names = [name for name, _ in stages]
    prior = _prior(stages, max(frames, 1), history or {})
    fraction = min(max(fraction, 0.0), 1.0)
    measured = sum(finished.values()) + (elapsed if current else 0.0)
    planned = sum(prior[s] for s in finished if s in prior) + (prior.get(current, 0.0) * fraction if current else 0.0)
    if prior["_absolute"]:  # history in seconds: damp this job's pace toward 1 while little is measured
        damping = PRIOR_WEIGHT * sum(prior[s] for s in names)
        pace = (measured + damping) / (planned + damping)
    elif planned > 0:  # the plan in weights only: seconds per weight unit, from what this job did
        pace = measured / planned
    else:
        return None
    out: dict[str, StageEta] = {}
    stage_left = 0.0
    for name in names:
        if name in finished and name != current:
            out[name] = StageEta(0.0, "done")
        elif name == current:
            stage_left = _running(prior[name] * pace, fraction, elapsed)
            rate = count.done / elapsed if count is not None and elapsed > 0 and count.done > 0 else None
            basis = "measured" if fraction > 0 else prior["_basis"].get(name, "weights")
            out[name] = StageEta(stage_left, basis, count.unit if count else None, rate)
        else:
            out[name] = StageEta(prior[name] * pace, prior["_basis"].get(name, "weights"))
    return Eta(sum(s.seconds_left for s in out.values()), stage_left, out)


def _running(expected: float, fraction: float, elapsed: float) -> float:
    """Seconds left of the running stage: its own rate, trusted as much as the share of it that is done."""
    planned_left = expected * (1.0 - fraction)
    if fraction <= 0.0 or elapsed <= 0.0:
        return max(planned_left, expected - elapsed, 0.0)
    own_left = elapsed * (1.0 - fraction) / fraction
    return fraction * own_left + (1.0 - fraction) * planned_left


def _prior(stages: Sequence[tuple[str, float]], frames: int, history: Mapping[str, float]) -> dict[str, Any]:
    """Expected seconds of each stage (history x frames; the rest by weight at the history's seconds per weight
    unit), with ``_absolute`` (whether they are seconds) and ``_basis`` per stage."""
    known = {name: history[name] * frames for name, _ in stages if history.get(name) is not None}
    weights = dict(stages)
    out: dict[str, Any] = {"_absolute": bool(known), "_basis": {n: "history" for n in known}}
    per_weight = sum(known.values()) / sum(weights[n] for n in known) if known and sum(weights[n] for n in known) else 1
    for name, weight in stages:
        out[name] = known.get(name, weight * per_weight)
    return out


def seconds_per_frame(jobs: Sequence[tuple[int, Mapping[str, float]]]) -> dict[str, float]:
    """Median seconds per input frame of each stage over earlier jobs (frames, stage seconds)."""
    samples: dict[str, list[float]] = {}
    for frames, timings in jobs:
        if frames <= 0:
            continue
        for name, seconds in timings.items():
            if isinstance(seconds, int | float) and seconds >= 0:
                samples.setdefault(name, []).append(float(seconds) / frames)
    return {name: sorted(v)[len(v) // 2] for name, v in samples.items()}
