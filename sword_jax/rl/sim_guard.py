"""Keeping GRPO in a learned simulator honest while the policy moves: guards against exploitation.

**The guard** (MBPO-style model trust, here measured rather than estimated): at every evaluation, GRPO in
the learned simulator replays real evaluation episodes in the simulator and scores them with the success
detector (:func:`sword_jax.rl.sim_agreement.replay_report`). The share of real failures the simulator and
detector call successes, the *false-success rate*, is what a policy exploiting the simulator drives up.
:class:`FalseSuccessGuard` keeps step 0's rate as the baseline and trips when an evaluation's rate exceeds it
by more than ``margin`` (with at least ``min_failures`` real failures replayed, so a handful of episodes
cannot trip it). The loop then rolls the policy back to the last checkpoint, which passed the guard
(:func:`sword_jax.rl.grpo_loop.train_grpo`).

**The real-success guard**: a run whose false-success rate is already high at step 0 leaves the first guard
no room (baseline + margin out of reach) while the policy gets worse in the real world. With refreshes
(:mod:`sword_jax.rl.refresh`) every refresh collects real episodes of the current policy, sampled as GRPO
samples, and records their success share (``real_success``). :class:`RealSuccessGuard` keeps the first judged
refresh's share (step 0's: the policy GRPO starts from) as the baseline and trips when a refresh's share falls
below it by more than ``margin`` (with at least ``min_episodes`` episodes; a skipped refresh is not judged).
The difference of two shares of 64 episodes each has a standard error of about 0.09, so a margin below ~0.15
trips on noise now and then.
"""

from __future__ import annotations

import dataclasses
from typing import Any


@dataclasses.dataclass(frozen=True)
class GuardDecision:
    """One evaluation's verdict: ``trip`` (roll back), the ``rate`` measured, the ``baseline`` and why."""

    trip: bool
    rate: float | None
    baseline: float | None
    reason: str


@dataclasses.dataclass
class FalseSuccessGuard:
    """Trips when the replay's false-success rate exceeds step 0's by more than ``margin`` (module docstring).

    ``baseline`` is set by the first report observed (step 0's); a resumed run passes it back in (the
    success curve keeps every evaluation's replay report, so it is read from step 0's point).
    """

    margin: float
    min_failures: int = 20
    baseline: float | None = None

    def __post_init__(self):
        if not 0.0 < self.margin < 1.0:
            raise ValueError(f"FalseSuccessGuard: margin must be in (0, 1), got {self.margin}")
        if self.min_failures < 1:
            raise ValueError(f"FalseSuccessGuard: min_failures must be >= 1, got {self.min_failures}")

    def observe(self, report: dict[str, Any] | None) -> GuardDecision:
        """The verdict on one evaluation's replay report (``replay_report``'s dict; ``None``/no replayed
        failures: nothing to judge, no trip). The first judged report sets the baseline."""
        entry = (report or {}).get("false_success") or {}
        rate, of = entry.get("rate"), int(entry.get("of") or 0)
        if rate is None or of < self.min_failures:
            return GuardDecision(False, rate, self.baseline, f"{of} real failures replayed (< {self.min_failures}): "
                                                             "not judged")
        if self.baseline is None:
            self.baseline = float(rate)
            return GuardDecision(False, rate, self.baseline, "baseline set")
        trip = rate > self.baseline + self.margin
        return GuardDecision(trip, rate, self.baseline,
                             f"false success {rate:.3f} {'>' if trip else '<='} baseline {self.baseline:.3f} + "
                             f"margin {self.margin:.3f} ({of} real failures)")


@dataclasses.dataclass
class RealSuccessGuard:
    """Trips when a refresh's real success falls below the first judged refresh's by more than ``margin``
    (module docstring).

    ``baseline`` is set by the first record judged (step 0's refresh); a resumed run passes it back in or
    observes the success curve's points again (each evaluation's point keeps its refresh record).
    """

    margin: float
    min_episodes: int = 32
    baseline: float | None = None

    def __post_init__(self):
        if not 0.0 < self.margin < 1.0:
            raise ValueError(f"RealSuccessGuard: margin must be in (0, 1), got {self.margin}")
        if self.min_episodes < 1:
            raise ValueError(f"RealSuccessGuard: min_episodes must be >= 1, got {self.min_episodes}")

    def observe(self, record: dict[str, Any] | None) -> GuardDecision:
        """The verdict on one evaluation's refresh record (``Refresher.refresh``'s dict; ``None``, a skipped
        refresh, one without ``real_success`` or of fewer than ``min_episodes`` episodes: nothing to judge,
        no trip). The first judged record sets the baseline."""
        if not record:
            return GuardDecision(False, None, self.baseline, "no refresh: not judged")
        rate, episodes = record.get("real_success"), int(record.get("real_episodes") or 0)
        if record.get("skipped"):
            return GuardDecision(False, None, self.baseline, f"refresh skipped ({record['skipped']}): not judged")
        if rate is None:
            return GuardDecision(False, None, self.baseline, "no real success recorded: not judged")
        if episodes < self.min_episodes:
            return GuardDecision(False, rate, self.baseline, f"{episodes} real episodes (< {self.min_episodes}): "
                                                             "not judged")
        rate = float(rate)
        if self.baseline is None:
            self.baseline = rate
            return GuardDecision(False, rate, self.baseline, f"baseline set ({episodes} real episodes)")
        trip = rate < self.baseline - self.margin
        return GuardDecision(trip, rate, self.baseline,
                             f"real success {rate:.3f} {'<' if trip else '>='} baseline {self.baseline:.3f} - "
                             f"margin {self.margin:.3f} ({episodes} real episodes)")
