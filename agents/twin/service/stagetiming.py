"""Which of the mirror's worker turns time their stages, and how much each timed figure counts for.

The mirror splits its worker thread's CPU by stage (`WorkerState.stage_cpu_s`, what `twin bench cost`
divides by the messages) with `time.thread_time`, which on a virtual machine can be a system call: 7.8 us a
call was measured on the project's 2-core VM, against 0.04 us for `time.monotonic`. A timed turn reads it
about eight times, about 60 us, which at batches of one message is more than decoding the message. So the
stages are timed on a sample of the turns and each timed figure is scaled by the inverse of its chance of
being timed (the Horvitz-Thompson estimator): the sums then estimate the whole CPU of each stage, without
bias from which turns are chosen, and an untimed turn reads no CPU clock at all.

- Each turn is timed with probability 1 / `STAGE_SAMPLE_EVERY`, independently of the others (the gaps between
  timed turns are drawn from the geometric distribution). A fixed "every 16th turn" would be cheaper to
  decide but could lock onto a periodic pattern (a worker alternating idle wake-ups and batches, say) and
  time only one kind of turn.
- A batch of `STAGE_TIMED_FROM` messages or more is always timed (with weight 1): the clock's cost, spread
  over its messages, is below a microsecond each, and the large batches, few but heavy, are where sampling
  would add the most noise. Its hand-over (read before the batch's size is known) is sampled like any turn.

A timed span also holds about one clock reading's own cost, which the scaling would count for the untimed
batches that no longer pay it; the mirror measures it on each timed batch (two more readings: about ten a
timed batch in all) and takes it off each span, never below zero (`mirror._span` says why). Even so, measured
at batches of one, the sampled stages read about 5 % high (docs/cost-per-message.md, "The stage timers,
sampled"), evenly over the stages, so each stage's share holds.

The totals per process (`twin bench cost` reads them from /proc through psutil) are exact either way; only
their split by stage is an estimate, whose spread shrinks with the number of timed batches
(`WorkerState.stage_timed_batches`).
"""

from __future__ import annotations

import math
import random

# One turn in this many, on average, is timed (batches of one message: about 10 clock reads of ~7.8 us every
# 16 messages, about 5 us a message instead of 60).
STAGE_SAMPLE_EVERY = 16
# Batches of this many messages or more are always timed: the clock's ~60 us is under 0.5 us a message.
STAGE_TIMED_FROM = 128


class StageSampler:
    """Decides, turn by turn, whether the worker times the turn's stages; `weight` is what a sampled turn's
    figures are multiplied by. `every=1` times every turn (weight 1). `rng` is for tests (a seeded
    `random.Random`); the default is a fresh generator, so no two mirrors sample in step."""

    __slots__ = ("_log_keep", "_rng", "_skip", "every", "weight")

    def __init__(self, every: int = STAGE_SAMPLE_EVERY, rng: random.Random | None = None) -> None:
        if every < 1:
            raise ValueError(f"every must be at least 1 (1 times every turn), not {every}")
        self.every = every
        self.weight = float(every)
        self._rng = rng if rng is not None else random.Random()
        # log(1 - p) of the geometric gap, computed once: the draw is only made on timed turns.
        self._log_keep = math.log1p(-1.0 / every) if every > 1 else 0.0
        self._skip = self._gap()

    def _gap(self) -> int:
        """How many turns to leave untimed before the next timed one: geometric with success 1/every, so
        each turn is timed with probability 1/every whatever came before it."""
        if self.every == 1:
            return 0
        # 1 - random() is in (0, 1], so the logarithm is finite; floor(log(U) / log(1 - p)) is geometric.
        return int(math.log(1.0 - self._rng.random()) / self._log_keep)

    def sample(self) -> bool:
        """Whether this turn is timed (called once a turn; an untimed turn costs a decrement)."""
        if self._skip:
            self._skip -= 1
            return False
        self._skip = self._gap()
        return True

    def batch_weight(self, sampled: bool, count: int) -> float:
        """What a batch of `count` messages' stage figures count for: 0 when it is not timed at all."""
        if count >= STAGE_TIMED_FROM:
            return 1.0
        return self.weight if sampled else 0.0


__all__ = ["STAGE_SAMPLE_EVERY", "STAGE_TIMED_FROM", "StageSampler"]
