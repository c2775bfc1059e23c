"""What a run tries when its own map contradicts itself: the back end's more conservative alternatives.

A map whose key frames contradict it (:func:`~slam_engine.evaluation.consistency.map_consistency`
flags it) is probably broken: parts of it offset or turned against each other. Before such a map is
handed over, the back end runs again with each alternative that the first run did not already try:

- the step check off (:mod:`step_rematch`), where it replaced steps: on the original Intel log with
  ODOM records paired at their jittered stamps, its replacements broke the map (20 % of the key frames
  contradicted, 0.36 m; 0.019 m without it);
- submaps twice as long, which close other revisits.

An alternative replaces the first map only when its map contradicts itself clearly less: at most
:data:`KEEP_AT_MOST` of the first map's share of contradicted key frames (sound building maps
contradict 0-6 % of their key frames, broken ones 10-20 %; outdoors, where foliage and cars are seen
through, sound and broken maps both come to 30-55 %, and a small difference says nothing). On open
ground the submap lengths are tried on every run already (:mod:`submap_choice`): that choice is the
retry there, and the step check, which holds the campus, stays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from slam_engine.backend.submap_choice import CheckedLoopClosing
from slam_engine.config import LoopClosingConfig

# an alternative's map replaces the first when its share of contradicted key frames is at most this
# share of the first's
KEEP_AT_MOST = 0.5


@dataclass
class FlaggedRetry:
    """The first map's share of contradicted key frames, each alternative tried with its share, and
    the one kept (None: the first map)."""

    first_share: float
    tried: list[tuple[str, float]] = field(default_factory=list)
    kept: str | None = None
    reason: str | None = None

    def summary(self) -> dict:
        out: dict = {"first_key_frames_contradicted_share": round(self.first_share, 4),
                     "alternatives": [{"alternative": name, "key_frames_contradicted_share": round(share, 4)}
                                      for name, share in self.tried],
                     "kept": self.kept or "the first map"}
        if self.reason is not None:
            out["reason"] = self.reason
        return out


def retry_alternatives(config: LoopClosingConfig, checked: CheckedLoopClosing) -> list[tuple[str, LoopClosingConfig]]:
    """The loop-closing settings to try on a flagged map, each named, in order (none with loop closing
    off, or where the submap lengths were all tried already)."""
    if not config.enabled or checked.tried:
        return []
    out = []
    if config.rematch_steps and checked.rematched.replaced:
        out.append(("step check off", config.model_copy(update={"rematch_steps": False})))
    longer = 2.0 * checked.submap_length_m
    if longer <= 1000.0:
        out.append((f"{longer:g} m submaps", config.model_copy(update={"submap_length_m": longer,
                                                                          "alternative_submap_lengths_m": []})))
    return out


def kept_alternative(first_share: float, shares: list[float]) -> int | None:
    """Index of the alternative whose map replaces the first (the least contradicted, the first of
    equal ones), or None when none contradicts at most :data:`KEEP_AT_MOST` of ``first_share``."""
    if not shares:
        return None
    best = min(range(len(shares)), key=lambda i: shares[i])
    return best if shares[best] <= KEEP_AT_MOST * first_share else None
