"""How long a running job has left, from rates measured on this job and on the service's earlier jobs.

A job's record keeps its ``work``: the number of input frames, each finished stage's seconds and unit count
(frames, pairs, blocks: what its progress reports count) and the running stage's start, share done and units
done. From it:

- **the running stage** goes at its own measured rate (share done per second: frames/s, pairs/s, blocks/s as
  its reports count them), blended with its expected time while little of it is done (weight: the share done);
- **the stages to come** take their expected time: seconds per unit of work measured for that stage on the
  service's recent jobs of the same pipeline (``history``), times this job's units, times how much slower or
  faster this job has run so far than those jobs predicted (``pace``, damped toward 1 early on). A stage's
  unit of work is the input frame, or for the stages whose cost follows the pixels the photos' own megapixel
  (reading them) or the working megapixel (rectifying, composing). A stage without history takes its pipeline weight
  (its planned share of the job) at the pace of the finished stages. A service without history of a pipeline
  starts from rates measured on a reference machine (``DEFAULT_RATES``).

Nothing here reads a clock or a database: callers pass the elapsed seconds and the history.
"""

from __future__ import annotations

import re
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

# "frame 4/12", "pair 3/20", "block 7/30", "load step 2/5"; the unit is the word(s) before the count
_COUNT = re.compile(r"([A-Za-z][A-Za-z ]*?)\s+(\d+)\s*/\s*(\d+)")
# What a stage's time follows (bench/eta.py: on 0.3 and 2.4 working MP per frame, compose_mosaic's seconds per
# frame differ 14x, match_features' 1.3x): the photos' own pixels (decoding them), the working pixels (what is
# rectified and composed), else the number of photos
PHOTO_PIXEL_STAGES = frozenset({"load_images", "orient_camera"})
PIXEL_STAGES = frozenset(
    {"compose_mosaic", "orthorectify_frames", "rectify_specimen", "detect_cracks", "write_crack_report"}
)
# ... or the pairs of photos matched (a grid has 3.7-4.1 of them per photo, a strip 2.5: per photo, the grids'
# matching cost 2.3x the strip's, per pair 1.6x), known once matching has planned them; until then
# PAIRS_PER_PHOTO of them per photo (the median of bench/eta.py's runs)
PAIR_STAGES = frozenset({"match_features", "measure_ties"})
PAIRS_PER_PHOTO = 3.7
# Seconds per unit of work (``work_unit``) of each stage on the reference machine (2 cores, wall seconds with
# other work on the machine): what a service with no history of its own starts from, its pace then measured on
# the job itself. Planar: the median of 12 runs of bench/eta.py (four times each the Brighton strip, 6 DJI
# photos of 9 MP at 2048 px, and 12- and 24-frame synthetic grids at 640 and 800 px); ortho: the Brighton strip
DEFAULT_RATES: dict[str, dict[str, float]] = {
    "mosaic": {
        "load_images": 0.025,
        "detect_features": 0.074,
        "match_features": 0.039,
        "measure_ties": 0.030,
        "align_frames": 0.040,
        "georeference": 0.0006,
        "compose_mosaic": 0.35,
        "write_report": 0.0095,
    },
    "mosaic.ortho": {
        "load_images": 0.024,
        "detect_features": 2.1,
        "match_features": 0.25,  # 0.62 s per photo, 15 pairs of 6 photos
        "adjust_bundle": 0.86,
        "orthorectify_frames": 1.45,  # 1.14 onto the tie points' surface; dense stereo took 1.27x that
        "compose_mosaic": 0.55,
        "write_report": 0.3,
    },
}
BASES = (
    "measured",
    "history",
    "defaults",
    "weights",
    "done",
)  # what a stage's time left comes from (core.labels names each)
# how much of a whole job the history's pace counts for against this job's own measured pace. A machine faster
# or slower than the one the rates came from shifts every stage alike, and a heavy prior held the estimate to
# the rates: at 0.3, runs of bench/eta.py on a quiet machine (2-2.5x the rates' pace) were off by 61-113 % of
# the job from a quarter done; at 0.02 by 11-16 %, and the runs on a busy one, where a stage's seconds vary up
# to 2x from run to run, by 8-19 % as at 0.3 (0.01-0.03 alike; tests/unit/data/eta_traces*.json)
PRIOR_WEIGHT = 0.02
# earlier jobs whose working megapixels per photo are within this factor of a job's predict it (history): the
# seconds per unit of small synthetic frames read, matched and tied 2-3x slower than the Brighton strip's
SIMILAR_SIZE = 2.0


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
    size: Mapping[str, float],
    finished: Mapping[str, float],
    current: str | None,
    fraction: float,
    elapsed: float,
    history: Mapping[str, float] | None = None,
    count: UnitCount | None = None,
    defaults: Mapping[str, float] | None = None,
) -> Eta | None:
    """The time left of a job whose pipeline runs ``stages`` (name, weight) in order over inputs of ``size``
    (``{"frames": n, "megapixels": working megapixels, "photo_megapixels": the photos' own}``).

    ``finished``: seconds of the stages done; ``current``: the running stage (None: waiting for the next one),
    ``fraction`` of it done after ``elapsed`` seconds, its last ``count``; ``history``: seconds per unit of work
    (``work_unit``) of each stage on earlier jobs; ``defaults``: the same where there is no history (a pipeline's
    ``DEFAULT_RATES``). None while nothing has been measured and there is neither.
    """
    names = [name for name, _ in stages]
    prior = _prior(stages, size, history or {}, defaults or {})
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
    """Seconds left of the running stage: its expected time less what has gone while it reports no share done
    yet (a parted stage's plan, e.g. a mosaic's gains and seams), then its own rate, trusted as much as the
    share of it that is done, and never less than what its expected time has left (a stage whose share done
    jumps ahead of its time, as a plan's or a last step's share can, is not taken to be nearly done)."""
    if fraction <= 0.0 or elapsed <= 0.0:
        return max(expected - elapsed, 0.0)
    planned_left = expected * (1.0 - fraction)
    own_left = elapsed * (1.0 - fraction) / fraction
    return max(fraction * own_left + (1.0 - fraction) * planned_left, expected - elapsed)


def work_unit(stage: str) -> str:
    """What a stage's time is counted per: ``photo_megapixels`` (the inputs' own pixels), ``megapixels`` (their
    working pixels), ``pairs`` (of photos matched) or ``frames``."""
    if stage in PHOTO_PIXEL_STAGES:
        return "photo_megapixels"
    if stage in PAIR_STAGES:
        return "pairs"
    return "megapixels" if stage in PIXEL_STAGES else "frames"


def _amount(stage: str, size: Mapping[str, float]) -> float | None:
    unit = work_unit(stage)
    value = size.get(unit)
    if unit == "pairs" and not (isinstance(value, int | float) and value > 0):
        value = PAIRS_PER_PHOTO * size["frames"] if isinstance(size.get("frames"), int | float) else None
    return float(value) if isinstance(value, int | float) and value > 0 else None


def _prior(
    stages: Sequence[tuple[str, float]],
    size: Mapping[str, float],
    history: Mapping[str, float],
    defaults: Mapping[str, float],
) -> dict[str, Any]:
    """Expected seconds of each stage (history, else the default rate, x its units; the rest by weight at their
    seconds per weight unit), with ``_absolute`` (whether they are seconds) and ``_basis`` per stage."""
    known, basis = {}, {}
    for name, _ in stages:
        amount = _amount(name, size)
        rate, source = (history[name], "history") if history.get(name) is not None else (defaults.get(name), "defaults")
        if rate is not None and amount is not None:
            known[name], basis[name] = rate * amount, source
    weights = dict(stages)
    out: dict[str, Any] = {"_absolute": bool(known), "_basis": basis}
    per_weight = sum(known.values()) / sum(weights[n] for n in known) if known and sum(weights[n] for n in known) else 1
    for name, weight in stages:
        out[name] = known.get(name, weight * per_weight)
    return out


def seconds_per_unit(
    jobs: Sequence[tuple[Mapping[str, float], Mapping[str, float]]], reference: Mapping[str, float] | None = None
) -> dict[str, float]:
    """Median seconds per unit of work (``work_unit``) of each stage over earlier jobs: (size, stage seconds);
    ``reference`` (a pipeline's ``DEFAULT_RATES``), when given, counts as one more job of the stages it has, so
    that one earlier job, slowed down by other work on the machine, is not all there is to go by."""
    samples: dict[str, list[float]] = {}
    if jobs and reference:
        for name, rate in reference.items():
            samples[name] = [float(rate)]
    for size, timings in jobs:
        for name, seconds in timings.items():
            amount = _amount(name, size)
            if amount is not None and isinstance(seconds, int | float) and seconds >= 0:
                samples.setdefault(name, []).append(float(seconds) / amount)
    return {name: statistics.median(v) for name, v in samples.items()}


def similar_jobs(
    jobs: Sequence[tuple[Mapping[str, float], Mapping[str, float]]], size: Mapping[str, float]
) -> list[tuple[Mapping[str, float], Mapping[str, float]]]:
    """The earlier jobs (size, stage seconds) whose working megapixels per photo are within ``SIMILAR_SIZE`` of
    a job of ``size``; all of them where that is not known."""
    mine = _per_frame(size)
    if mine is None:
        return list(jobs)
    return [
        job for job in jobs if (theirs := _per_frame(job[0])) is None or 1 / SIMILAR_SIZE < theirs / mine < SIMILAR_SIZE
    ]


def _per_frame(size: Mapping[str, float]) -> float | None:
    frames, pixels = size.get("frames"), size.get("megapixels")
    return float(pixels) / float(frames) if frames and pixels and frames > 0 and pixels > 0 else None


def working_megapixels(sizes: Sequence[tuple[int, int]], working_max_px: int | None) -> float:
    """Megapixels of the inputs as the stages handle them: each (width, height) reduced to ``working_max_px`` on
    its longer side (None: at full size)."""
    total = 0.0
    for width, height in sizes:
        scale = 1.0 if not working_max_px else min(1.0, working_max_px / max(width, height, 1))
        total += width * height * scale * scale / 1e6
    return total
