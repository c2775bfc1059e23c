"""SLAM configuration: one nested pydantic model, documented defaults and units, saved with every
result. Bounds on every field keep a run's cost finite.

Loading lives here too, for every caller (CLI, service, benchmark): :func:`load_config` reads a YAML or
JSON file and merges overrides section by section, :func:`validate_config` turns a mapping into a
``SlamConfig`` with one readable error, :func:`defaults_yaml` prints the documented defaults."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from slam_engine.errors import ConfigError


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


SubmapLength = Annotated[float, Field(gt=0.0, le=1000.0)]  # travel per submap [m]


class GridConfig(_Section):
    """Log-odds occupancy grid."""

    resolution_m: float = Field(0.05, ge=0.01, le=1.0, description="Cell size [m].")
    log_odds_hit: float = Field(0.9, gt=0.0, le=10.0, description="Added to a beam's end cell.")
    log_odds_miss: float = Field(-0.4, lt=0.0, ge=-10.0, description="Added to cells a beam crosses.")
    log_odds_min: float = Field(-5.0, ge=-50.0, lt=0.0, description="Lower clamp.")
    log_odds_max: float = Field(5.0, gt=0.0, le=50.0, description="Upper clamp.")
    max_range_m: float = Field(30.0, gt=0.1, le=200.0, description="Beams are used up to this range [m]; "
                               "longer returns clear free space to here but add no hit.")
    no_return_clear_m: float = Field(30.0, ge=0.0, le=200.0, description="Beams without a return clear free "
                                     "space up to this range [m], capped by max_range_m and the sensor's range "
                                     "(0 = not at all; lower it for scanners that report no return for dark or "
                                     "glass surfaces close by, e.g. Hokuyo URG-04LX zeros).")
    no_return_min_sensor_range_m: float = Field(10.0, ge=0.0, le=200.0, description="No-return beams of "
                                                "scanners whose maximum range is below this [m] clear "
                                                "nothing: short-range scanners (Hokuyo URG-04LX, 5.6 m) "
                                                "report no return for dark or glass surfaces well within "
                                                "range, and clearing along those beams erases walls.")
    no_return_bounded: bool = Field(True, description="A beam without a return clears only up to the line "
                                    "joining the returns of the nearest returned beams on either side of it "
                                    "(a window in a wall stops at the wall: no rays around buildings) in the "
                                    "product map; False = clear the whole no_return_clear_m. The particles' "
                                    "own maps, which the scans are matched on, always take every beam.")
    no_return_open_share: float = Field(0.15, ge=0.0, le=1.0, description="A drive whose level LiDAR returned "
                                        "nothing on more than this share of its beams is on open ground "
                                        "(the Freiburg campus 26 %; buildings 0-2.5 %, a street 11.5 %) and is "
                                        "mapped with no_return_clear_m 0: there those beams cleared what the "
                                        "next pass hit. Batch runs only (a live job keeps no_return_clear_m); "
                                        "1 = never.")
    no_return_stop_short_m: float = Field(0.5, ge=0.0, le=10.0, description="Bounded no-return beams stop "
                                          "this far [m] short of the line joining their bracketing returns, so "
                                          "that they do not clear the wall cells they meet at a slant.")


class MotionNoiseConfig(_Section):
    """Odometry motion-model noise (rot1-trans-rot2), proportional to the motion: standing still
    adds no noise."""

    rot_from_rot: float = Field(0.1, ge=0.0, le=2.0, description="sd(rot) per |rot| [rad/rad].")
    rot_from_trans: float = Field(0.05, ge=0.0, le=2.0, description="sd(rot) per metre [rad/m].")
    trans_from_trans: float = Field(0.05, ge=0.0, le=2.0, description="sd(trans) per metre [m/m].")
    trans_from_rot: float = Field(0.02, ge=0.0, le=2.0, description="sd(trans) per |rot| [m/rad].")


class HeadingCalibrationConfig(_Section):
    """Online estimate of the odometry's systematic heading error (turn scale, drift per metre),
    measured by the scan matcher and corrected before sampling the motion."""

    enabled: bool = Field(True, description="Estimate and correct the odometry's heading scale and drift.")
    prior_scale_rad2: float = Field(0.5, gt=0.0, le=1000.0, description="Weight of the prior 'scale = 1', "
                                    "in squared radians of odometry turn it is worth (more = slower to move).")
    prior_drift_m2: float = Field(10.0, gt=0.0, le=100000.0, description="Weight of the prior 'drift = 0', "
                                  "in squared metres of travel it is worth.")
    scale_band: float = Field(0.1, ge=0.0, le=1.0, description="Dead band of the turn-scale correction: "
                              "the estimate is used once it is this far from 1 (smaller errors are left to the "
                              "scan matcher).")
    drift_band_rad_per_m: float = Field(0.01, ge=0.0, le=1.0, description="Dead band of the drift "
                                        "correction [rad/m]: the estimate is used once it is this far from 0.")
    prior_distance_m2: float = Field(100.0, gt=0.0, le=100000.0, description="Weight of the prior 'distance "
                                     "scale = 1', in squared metres of travel it is worth (the distance scale "
                                     "is measured where the scan constrains the direction of travel).")
    distance_band: float = Field(0.02, ge=0.0, le=1.0, description="Dead band of the distance-scale "
                                 "correction: used once the estimate is this far from 1.")


class OdometryConfig(_Section):
    """How scans are paired with the odometry: the time offset between the LiDAR's stamps and the
    odometry's clock (estimated online from the matched turns, :mod:`slam_engine.frontend.time_offset`) and the
    de-skew of scans swept while the vehicle moved."""

    time_offset_s: Literal["auto"] | Annotated[float, Field(ge=-1.0, le=1.0)] = Field(
        "auto", description="A scan stamped t was measured at t + this on the odometry's clock [s], within "
        "-1 and 1 (a scan that lags the wheel ticks by 0.15 s: -0.15). 'auto': estimated online and applied "
        "once confident and outside time_offset_band_s; a number: always that (the estimate is still "
        "reported; 0 = pair scans with the odometry at their stamps).")
    time_offset_max_s: float = Field(0.3, ge=0.01, le=1.0, description="'auto' looks for the offset within "
                                     "+- this [s] (a scan counts for the estimate once the odometry has passed "
                                     "its stamp by this much).")
    time_offset_band_s: float = Field(0.02, ge=0.0, le=1.0, description="Dead band [s]: an estimate smaller "
                                      "than this is not applied (the matcher absorbs it).")
    time_offset_min_evidence: float = Field(50.0, ge=0.0, le=1e6, description="The estimate is applied once "
                                            "the matched turns fit it better than no offset by this many mean "
                                            "squared residuals (intel, without an offset, reaches 21; exp2 80 "
                                            "after 20 scans) ...")
    time_offset_max_se_s: float = Field(0.02, gt=0.0, le=1.0, description="... its standard error is below "
                                        "this [s] ...")
    time_offset_min_steps: int = Field(10, ge=1, le=100000, description="... and this many processed scans "
                                       "have measured it.")
    time_offset_prior_weight: float = Field(0.05, gt=0.0, le=1000.0, description="Weight of the prior "
                                            "'offset = 0' [rad^2/s^2 of squared turn residual].")
    deskew: bool = Field(True, description="Move each beam's end point by the odometry's motion between its "
                         "time and the scan's middle (only for LiDAR models with a time increment per beam: "
                         "BreezySLAM's URG-04LX from its specification, ROS scans that carry one).")


class MatcherConfig(_Section):
    """Scan-matched proposal: local search around each particle's odometry prediction."""

    search_xy_m: float = Field(0.3, ge=0.0, le=5.0, description="Smallest half width of the xy search window "
                               "[m]; the window is search_sigmas standard deviations of the predicted motion "
                               "error, at least this and at most max_search_xy_m.")
    search_theta_rad: float = Field(0.2, ge=0.0, le=1.5, description="Smallest half width of the heading "
                                    "window [rad] (likewise).")
    search_sigmas: float = Field(3.0, gt=0.0, le=10.0, description="Search window in standard deviations of "
                                 "the motion model's predicted error.")
    max_search_xy_m: float = Field(1.5, ge=0.0, le=10.0, description="Largest half width of the xy window [m].")
    max_search_theta_rad: float = Field(0.6, ge=0.0, le=3.0, description="Largest half width of the heading "
                                        "window [rad]. Windows wider than the smallest are searched "
                                        "correlatively on the coarsest map level before the fit.")
    proposal: Literal["match", "fused"] = Field("match", description="'match': a particle takes its fitted pose; "
                                                "'fused': the fit combined with the motion sample by their "
                                                "information (keeps precise odometry where the scan adds little).")
    proposal_information: float = Field(5.0, gt=0.0, le=1000.0, description="With proposal 'fused': the fit's "
                                        "information is its Gauss-Newton matrix times the likelihood gain times "
                                        "this.")
    motion_prior: float = Field(0.7, ge=0.0, le=10.0, description="Weight of the motion prior in a particle's "
                                "importance weight: the scan's log likelihood at the fit less this times half the "
                                "squared Mahalanobis distance of the fit from the predicted pose (covariance: the "
                                "motion's plus the fit's own). 0: the scan's likelihood alone, which let single "
                                "particles that snapped 0.45 rad off a 0.09 rad prediction win on "
                                "infinite-corridor-rough; 1: a particle whose fit was rejected (no prior to pay) "
                                "outweighed one that matched a turn the odometry under-reported (aces-rough at 15 "
                                "particles: 3 maps of 20 lost, none at 0.7).")
    sigma_m: float = Field(0.05, gt=0.0, le=2.0, description="Std. dev. of the endpoint likelihood [m]; an end "
                           "point's distance to the wall is taken as (1 - M) cells, M = map value in [0, 1].")
    beam_skip: int = Field(1, ge=1, le=50, description="Use every n-th beam for matching.")
    max_points: int = Field(400, ge=10, le=100000, description="Match with at most this many end points "
                            "(dense scans are thinned evenly, after beam_skip). 400 keeps every beam of a "
                            "360-beam SICK and every other one of a 682-beam URG-04LX: against 200, "
                            "freiburg-079 0.0189 m instead of 0.0206 (for 25 % more time), exp2's half "
                            "agreement 0.513 instead of 0.493, the simulated car's worst ATE 0.068 m "
                            "instead of 0.115; 180-beam logs are unchanged.")
    independent_beams: float = Field(40.0, gt=0.0, le=10000.0, description="How many independent "
                                     "measurements a scan counts as when weighting particles (beams are "
                                     "correlated; fewer = smoother weights).")
    min_score: float = Field(0.3, ge=0.0, le=1.0, description="Below this normalised score the "
                             "odometry proposal is used instead of the match.")
    local_map_m: float = Field(30.0, ge=0.0, le=100000.0, description="Particles match against their local map: "
                               "map tiles no scan touched in this much travel [m] are forgotten (kept for "
                               "previews), so that a place mapped long ago is not matched where the drift puts "
                               "it; the back end closes those loops. 0: keep the whole map.")


class LocalizationConfig(_Section):
    """Placing a drive, or another map, in a saved map (:mod:`slam_engine.multisession`): a global search
    over the whole map with a stretch of the drive, confirmed by a second, disjoint stretch, then each
    scan tracked against the map."""

    stretch_m: float = Field(4.0, gt=0.0, le=100.0, description="Travel per stretch of the drive that is "
                             "searched for over the whole map, its scans joined by the odometry [m].")
    local_map_m: float = Field(8.0, gt=0.0, le=100.0, description="Each scan of the drive is first matched "
                               "against its own scans of this much travel before it, which corrects the odometry "
                               "between scans [m].")
    local_map_resolution_m: float = Field(0.1, ge=0.02, le=1.0, description="Cell size of the grid of the "
                                          "drive's own recent scans that each scan is matched against [m].")
    search_resolution_m: float = Field(0.2, ge=0.02, le=1.0, description="Cell size of the global search's "
                                       "grid [m] (the pose is then refined on the map's own cells).")
    from_places: bool = Field(True, description="A stretch searched for over the whole map finds its best pose "
                              "only around the place_candidates places the map's place index proposes (within "
                              "place_index.window_m / window_rad of each), on the whole-map search's lattice, and its "
                              "runner-up over the whole map: the whole-map search's verdict where the index holds the "
                              "place, too low or ambiguous (never a wrong placement) where it misses it. Off: every "
                              "such stretch is searched for over the whole map.")
    place_candidates: int = Field(20, ge=1, le=200, description="See from_places: the places proposed per stretch, "
                                  "best first (5 missed aces-rough-b's first placement on seed 1).")
    min_score: float = Field(0.65, ge=0.0, le=1.0, description="Lowest mean blurred hit value under a "
                             "stretch's end points for a global placement (0-1).")
    runner_up_ratio: float = Field(0.9, gt=0.0, le=1.0, description="A placement is ambiguous when a pose "
                                   "farther than ambiguity_m scores at least this share of the best.")
    ambiguity_m: float = Field(1.0, ge=0.0, le=100.0, description="See runner_up_ratio [m].")
    ambiguity_rad: float = Field(0.15, ge=0.0, le=3.2, description="... or turned this much [rad].")
    agree_m: float = Field(0.3, gt=0.0, le=10.0, description="The second stretch's placement agrees with the "
                           "first (tracked to it) within this distance [m] ...")
    agree_rad: float = Field(0.1, gt=0.0, le=3.2, description="... and this heading difference [rad].")
    max_seen_through: float = Field(0.1, ge=0.0, le=1.0, description="A placement (both stretches) is refused "
                                    "when more than this share of its end points on cells the map observed fall "
                                    "where the map saw free space, seen_through_margin_m or more from anything "
                                    "else: the drive's walls stand in the map's rooms (a look-alike building).")
    seen_through_margin_m: float = Field(0.2, ge=0.0, le=5.0, description="See max_seen_through [m].")
    max_seen_through_track: float = Field(0.3, ge=0.0, le=1.0, description="A live localisation's scan is not "
                                          "found when more than this share of the end points of the scans matched "
                                          "over its last 2 m fall where the map saw free space (see "
                                          "max_seen_through): a robot carried off to a look-alike place.")
    track_window_m: float = Field(0.5, gt=0.0, le=10.0, description="Each scan is searched for within this "
                                  "distance of where the odometry puts it [m] ...")
    track_window_rad: float = Field(0.3, gt=0.0, le=3.2, description="... and this turn [rad].")
    track_min_score: float = Field(0.5, ge=0.0, le=1.0, description="A scan whose match scores below this is "
                                   "placed by the odometry alone (confidence = its score; 0 below 0.6 of the lowest "
                                   "score a scan is found with: it matched nowhere) ...")
    nudge_min_score: float = Field(0.3, ge=0.0, le=1.0, description="... unless it scores at least this and moves "
                                   "the scan by no more than nudge_m / nudge_rad from where the odometry puts it.")
    nudge_m: float = Field(0.1, ge=0.0, le=10.0, description="See nudge_min_score [m].")
    nudge_rad: float = Field(0.05, ge=0.0, le=3.2, description="See nudge_min_score [rad].")
    window_per_m: float = Field(0.05, ge=0.0, le=1.0, description="The tracking window grows by this much per "
                                "metre travelled since the last scan that matched [m/m] ...")
    window_rad_per_m: float = Field(0.02, ge=0.0, le=1.0, description="... and its turn by this [rad/m].")
    lost_after_m: float = Field(10.0, gt=0.0, le=10000.0, description="No scan matched over this much travel "
                                "within the map's observed area: the drive is lost, and searched for again [m].")
    max_points: int = Field(250, ge=10, le=100000, description="A stretch is searched with at most this many "
                            "end points.")
    max_map_key_frames: int = Field(20000, ge=100, le=10_000_000, description="An extended or merged map "
                                    "keeps at most this many key frames: beyond, the oldest drives' key frames "
                                    "that a newer one sees from nearby are dropped (lifelong use).")
    prune_m: float = Field(0.5, gt=0.0, le=100.0, description="... from within this distance [m] ...")
    prune_rad: float = Field(0.3, gt=0.0, le=3.2, description="... and this heading difference [rad].")
    max_first_tries: int = Field(12, ge=1, le=10000, description="Stretches searched for the drive's first "
                                 "placement, spread over the drive; none placed: the drive is refused.")
    own_loops_after_m: float = Field(20.0, ge=0.0, le=10000.0, description="A drive that went this far [m] "
                                     "without a scan matching the map (where the map never saw) has its own loops "
                                     "closed too, by the back end's loop closer over its scans, and the pose graph "
                                     "that smooths it takes those closures with the map's matches: aces-rough-b "
                                     "(35 m out) 0.29 -> 0.07 m on its own relations, in 0.15 s more. Below, it "
                                     "costs more than it gains (intel-b, 14 m out: 0.035 -> 0.032 m in 0.45 s "
                                     "more). 0: always.")
    live_lost_after_m: float = Field(2.0, gt=0.0, le=10000.0, description="A live localisation (scan by scan) "
                                     "calls the drive lost after this much travel [m] over scans the map could "
                                     "judge but none matched, and searches the whole map again: a robot carried "
                                     "off is found again within a few metres (a finished drive waits "
                                     "lost_after_m: it has the scans after to judge by).")
    live_stretch_m: float = Field(2.0, gt=0.0, le=100.0, description="stretch_m of a live localisation's "
                                  "searches [m]: shorter, to place the drive sooner (a finished drive's "
                                  "localisation keeps 4 m: its re-finds in aces-rough-b are fewer with 2-3 m).")
    own_loops: bool = Field(True, description="Close the drive's own loops (see own_loops_after_m); off: a "
                            "drive out of the map is carried by its scan-to-scan matches alone.")


class LoopClosingConfig(_Section):
    """The back end: submaps along the front end's key frames, loop closures verified by a global
    correlative match, and a pose graph with a robust loss (:mod:`slam_engine.backend`)."""

    enabled: bool = Field(True, description="Close loops and optimise the trajectory after the filter.")
    odometry_smoothing: bool = Field(True, description="Where the log's odometry is locally more precise than "
                                     "the final key-frame poses (measured on the log: those poses against odometry "
                                     "over 1-16 key frames), tie consecutive key frames by it in a final smoothing.")
    map_alignment_passes: int = Field(3, ge=0, le=10, description="After the pose graph, fit every key frame's "
                                      "scan onto the map of all of them this many times (each onto the map of the "
                                      "last fits) and combine the fits with the graph's poses by their measured "
                                      "noise (0: keep the graph's poses).")
    rematch_steps: bool = Field(True, description="Before loop closing, score each key frame's scan where the "
                                "front end's step puts it on the map of the key frames just before it, and replace a "
                                "step that fits poorly by a clearly better, unique fit nearby (a step whose heading "
                                "is off bends its submap; outdoors, tens per drive).")
    rematch_key_frames: int = Field(10, ge=1, le=100, description="The map a step is checked against: this many "
                                    "key frames before it, as placed so far.")
    rematch_below_score: float = Field(0.3, ge=0.0, le=1.0, description="A step whose scan scores below this "
                                       "there is searched for anew ...")
    rematch_window_m: float = Field(1.0, gt=0.0, le=10.0, description="... within this half width [m] ...")
    rematch_window_rad: float = Field(0.5, gt=0.0, le=3.2, description="... and this heading half width [rad] "
                                      "of where the step put it ...")
    rematch_min_score: float = Field(0.12, ge=0.0, le=1.0, description="... and replaced by the pose found when "
                                     "it scores at least this ...")
    rematch_gain: float = Field(0.1, ge=0.0, le=1.0, description="... and this much more than the step's pose "
                                "(and no pose 0.5 m or 0.2 rad away comes within runner_up_ratio of it).")
    rematch_unverified: bool = Field(True, description="Search every step the front end left unverified (its "
                                     "match rejected), whatever it scores; off on open ground, where it made the "
                                     "campus worse (docs/engine.md).")
    submap_length_m: SubmapLength = Field(8.0, description="Travel per submap [m].")
    alternative_submap_lengths_m: list[SubmapLength] = Field(
        default_factory=list, max_length=4, description="Loops are also closed with each of these submap "
        "lengths [m] (each in (0, 1000]), and the result whose key frames contradict its map least is kept "
        "(the back end's time times the lengths tried); empty: only submap_length_m.")
    open_ground_alternative_submap_lengths_m: list[SubmapLength] = Field(
        default_factory=lambda: [16.0], max_length=4, description="alternative_submap_lengths_m on open ground "
        "(grid.no_return_open_share; batch runs) where none are set: outdoors 8 m and 16 m submaps each "
        "gave the better campus map on about half of the seeds.")
    submap_max_nodes: int = Field(80, ge=2, le=100000, description="At most this many key frames per submap.")
    search_every_m: float = Field(0.5, ge=0.0, le=100.0, description="Look for loops every this much travel [m].")
    min_loop_travel_m: float = Field(10.0, ge=0.0, le=10000.0, description="A submap is a loop candidate once "
                                     "the drive has gone this far since its last key frame [m].")
    candidates_per_search: int = Field(3, ge=1, le=50, description="Match at most this many nearest submaps.")
    overlap_m: float = Field(3.0, ge=0.0, le=100.0, description="A submap is in reach when one of its key frames "
                             "lies within the search window plus this distance [m].")
    base_window_m: float = Field(0.5, gt=0.0, le=50.0, description="Search half width right after a closure [m].")
    window_per_m: float = Field(0.08, ge=0.0, le=1.0, description="Growth of the search half width per metre "
                                "travelled since the last closure [m/m].")
    max_window_m: float = Field(15.0, gt=0.0, le=100.0, description="Largest search half width [m].")
    base_window_rad: float = Field(0.1, gt=0.0, le=3.2, description="Heading search half width right after a "
                                   "closure [rad].")
    window_rad_per_m: float = Field(0.01, ge=0.0, le=1.0, description="Its growth per metre travelled [rad/m].")
    max_window_rad: float = Field(0.6, gt=0.0, le=3.2, description="Largest heading search half width [rad].")
    match_range_m: float = Field(20.0, gt=0.5, le=200.0, description="End points farther than this from the "
                                 "LiDAR are not used for loop closing [m].")
    max_points: int = Field(250, ge=10, le=100000, description="A key frame matches with at most this many points.")
    match_span_m: float = Field(4.0, ge=0.0, le=100.0, description="A key frame is matched together with the "
                                "key frames over this much travel before it [m], placed by the front end's "
                                "motion: a stretch of corridor is told apart from another where one scan is not "
                                "(0: the key frame's own scan alone).")
    unobserved_score: float = Field(0.3, ge=0.0, le=1.0, description="What an end point scores where no scan "
                                    "of the submap looked (neither a hit nor a miss: the submap cannot contradict "
                                    "it); seen free space scores 0, a hit 1.")
    min_score: float = Field(0.6, ge=0.0, le=1.0, description="Lowest mean blurred hit value under the scan's end "
                             "points for a closure.")
    open_ground_min_score: float = Field(0.5, ge=0.0, le=1.0, description="min_score on open ground "
                                         "(grid.no_return_open_share; batch runs), where a revisit's scan scores "
                                         "about 0.5 at its true pose (foliage, cars and people change between "
                                         "passes); the lower of the two is used.")
    min_score_wide: float = Field(0.7, ge=0.0, le=1.0, description="Lowest score of a closure found with a "
                                  "window wider than confirm_window_m (more poses tried, more chance of a false "
                                  "match).")
    overlap_min_score: float = Field(0.55, ge=0.0, le=1.0, description="A pose closure that moves its key frame "
                                     "over 2 m is rejected when the points that overlap the submap's seen cells at "
                                     "the pose found score below this (they were picked at the predicted pose).")
    edge_share: float = Field(0.9, gt=0.0, le=1.0, description="A match this far out in its window (share of "
                              "the half width) is rejected: the best pose may lie beyond it.")
    ambiguity_m: float = Field(1.0, ge=0.0, le=100.0, description="A second pose this far from the best [m] ...")
    ambiguity_rad: float = Field(0.15, ge=0.0, le=3.2, description="... or this far in heading [rad] ...")
    runner_up_ratio: float = Field(0.9, gt=0.0, le=1.0, description="... scoring at least this share of the "
                                   "best makes the match ambiguous: rejected, or a heading closure.")
    heading_closures: bool = Field(True, description="A match that is ambiguous only along a line (a corridor: "
                                   "every pose along it fits as well, and a parallel corridor may be in the "
                                   "window instead of the true one) still fixes the heading.")
    heading_closure_max_turn_rad: float = Field(0.2, gt=0.0, le=3.2, description="A key frame whose best "
                                                "match is a heading closure turning it more than this "
                                                "[rad] closes no loop there: a line alone, turned that far, "
                                                "is as likely another straight wall (the corridor's heading "
                                                "closures turn theirs at most 0.15 rad).")
    line_half_width_m: float = Field(0.3, gt=0.0, le=10.0, description="The line runs through the best pose "
                                     "and the runner-up (which must lie within line_half_width_rad of the best's "
                                     "heading); no pose farther than this from it [m] may score within "
                                     "runner_up_ratio.")
    line_half_width_rad: float = Field(0.03, gt=0.0, le=1.0, description="Largest heading difference between "
                                       "the best pose and the runner-up on a line [rad].")
    confirm_window_m: float = Field(1.5, ge=0.0, le=100.0, description="Closures found with a wider window "
                                    "than this [m] wait for a second, agreeing one.")
    confirm_m: float = Field(0.3, gt=0.0, le=10.0, description="Two closures agree within this distance [m] ...")
    confirm_rad: float = Field(0.05, gt=0.0, le=3.2, description="... and this heading difference [rad].")
    confirm_travel_m: float = Field(5.0, gt=0.0, le=1000.0, description="The agreeing closure must come within "
                                    "this much travel [m].")
    reoptimize_m: float = Field(0.2, ge=0.0, le=100.0, description="Optimise the graph at once when a closure "
                                "moves its key frame more than this [m] ...")
    reoptimize_rad: float = Field(0.03, ge=0.0, le=3.2, description="... or turns it more than this [rad].")
    motion_sd_m: float = Field(0.01, gt=0.0, le=10.0, description="Front-end motion edges: sd [m] ...")
    motion_sd_per_m: float = Field(0.02, ge=0.0, le=10.0, description="... plus this per metre moved [m/m].")
    motion_sd_rad: float = Field(0.003, gt=0.0, le=3.2, description="Heading sd of a motion edge [rad] ...")
    motion_sd_rad_per_rad: float = Field(0.02, ge=0.0, le=10.0, description="... plus this per radian turned ...")
    motion_sd_rad_per_m: float = Field(0.005, ge=0.0, le=10.0, description="... plus this per metre [rad/m].")
    unverified_sd_m: float = Field(0.3, gt=0.0, le=100.0, description="A motion edge that the front end did not "
                                   "verify by a scan match (the particle kept its motion sample): sd [m] ...")
    unverified_sd_rad: float = Field(0.3, gt=0.0, le=3.2, description="... and heading sd [rad].")
    unverified_travel_m: float = Field(25.0, ge=0.0, le=1000.0, description="Such a step widens the closure "
                                       "search windows across it as this much travel would [m].")
    closure_sd_m: float = Field(0.05, gt=0.0, le=10.0, description="Closure edges: sd [m].")
    closure_sd_rad: float = Field(0.01, gt=0.0, le=3.2, description="Closure edges: heading sd [rad].")
    cauchy_scale: float = Field(1.0, gt=0.0, le=100.0, description="Scale of the Cauchy loss on closure edges "
                                "(in standard deviations).")
    far_search: bool = Field(True, description="Where no window can reach the map far behind any more (the "
                             "drift since the last closure exceeds what max_window_m holds), stretches of the drive "
                             "are searched for over the whole map behind them (branch and bound, every heading) "
                             "and a confirmed placement becomes a closure: loops that come back after hundreds of "
                             "metres without one (outdoors).")
    far_every_m: float = Field(20.0, gt=0.0, le=1000.0, description="Travel between far searches [m].")
    far_min_gap_m: float = Field(60.0, gt=0.0, le=100000.0, description="A far search looks only at key frames "
                                 "at least this much travel behind the stretch [m].")
    far_stretch_m: float = Field(8.0, gt=0.0, le=100.0, description="Travel per stretch searched for [m]; the "
                                 "stretch before it, searched for on its own, must land where the front end's "
                                 "motion puts it.")
    far_resolution_m: float = Field(0.2, ge=0.02, le=1.0, description="Cell size of the far search's grid [m].")
    far_min_score: float = Field(0.65, ge=0.0, le=1.0, description="Lowest score of a far placement (both "
                                 "stretches).")
    far_second_pass_m: float = Field(30.0, ge=0.0, le=100000.0, description="A far closure that moves its key "
                                     "frame farther than this [m] sends the back end through the key frames once "
                                     "more, from the corrected poses (their windowed searches had started from "
                                     "estimates too far off).")
    far_rebuild_m: float = Field(50.0, gt=0.0, le=10000.0, description="The map behind is indexed anew when "
                                 "this much travel was added to it [m] (or a closure moved it).")


class SchedulingConfig(_Section):
    """When to process a scan (odometry is integrated continuously)."""

    linear_update_m: float = Field(0.2, ge=0.0, le=10.0, description="Process after this much travel [m].")
    angular_update_rad: float = Field(0.1, ge=0.0, le=3.2, description="... or this much rotation [rad].")
    temporal_update_s: float = Field(0.0, ge=0.0, le=3600.0, description="... or this much time [s]; 0 = off.")


class LidarFilterConfig(_Section):
    """Per-scan point filtering for LiDARs mounted with a 3-D extrinsic."""

    ground_z_m: float = Field(0.2, ge=-5.0, le=5.0, description="Points below this height in the vehicle "
                              "frame are ground hits and dropped [m].")
    ceiling_z_m: float = Field(20.0, ge=-5.0, le=50.0, description="Points above this height are dropped [m] "
                               "(tree tops, overhangs). A tilted LiDAR sees building walls high up: they "
                               "are kept, projected onto the plane.")


class TextureConfig(_Section):
    """Ground texture map from stereo or RGB-D cameras, built after the trajectory is known."""

    enabled: bool = Field(True, description="Build a texture map when the log has camera data.")
    ground_z_m: float | None = Field(None, ge=-5.0, le=5.0, description="Height of the ground in the "
                                     "vehicle/world frame [m]; None = estimate it (RANSAC plane fit).")
    ground_band_m: float = Field(0.15, gt=0.0, le=2.0, description="Points within this distance of "
                                 "the ground height are ground [m].")
    cell_mode: Literal["mean", "latest"] = Field("mean", description="Per cell: running mean of all "
                                                 "observations, or the latest frame's colour.")
    min_depth_m: float = Field(0.3, ge=0.0, le=50.0, description="Nearer points are dropped [m].")
    max_depth_m: float = Field(10.0, gt=0.1, le=200.0, description="Farther points are dropped [m] "
                               "(stereo depth error grows with the square of the depth).")
    rgbd_max_depth_m: float = Field(4.0, gt=0.1, le=20.0, description="Farther RGB-D points are dropped "
                                    "[m] (Kinect v1 depth steps reach ~0.05 m at 3 m, ~0.1 m at 4 m).")
    frame_stride: int = Field(1, ge=1, le=1000, description="Use every n-th camera frame.")
    max_frames: int = Field(3000, ge=1, le=100000, description="At most this many frames, spread "
                            "evenly over the drive.")
    max_time_gap_s: float = Field(0.1, ge=0.0, le=5.0, description="A frame is used only within this "
                                  "time of the trajectory's span, and RGB is paired with depth "
                                  "frames at most this far apart [s].")
    stereo_width_scale: float = Field(0.5, ge=0.125, le=1.0, description="Stereo disparity is computed on "
                                      "the rectified pair narrowed to this fraction of its width (columns "
                                      "averaged; rows, which sample far ground sparsely, are kept); 1 = full "
                                      "width. 0.5 matches in about a third of the time.")
    sgbm_num_disparities: int = Field(128, ge=16, le=512, multiple_of=16, description="StereoSGBM "
                                      "disparity search range [px].")
    sgbm_block_size: int = Field(5, ge=1, le=31, description="StereoSGBM block size [px], odd.")
    sgbm_uniqueness_ratio: int = Field(10, ge=0, le=100, description="StereoSGBM uniqueness margin [%].")
    sgbm_speckle_window: int = Field(100, ge=0, le=1000, description="StereoSGBM speckle filter "
                                     "window [px]; 0 = off.")
    sgbm_speckle_range: int = Field(2, ge=0, le=64, description="StereoSGBM speckle disparity range [px].")

    @field_validator("sgbm_block_size")
    @classmethod
    def _odd_block(cls, value: int) -> int:
        if value % 2 == 0:
            raise ValueError("sgbm_block_size must be odd")
        return value


class PlaceIndexConfig(_Section):
    """The place index (:mod:`slam_engine.backend.place_index`): polar descriptors of a map around places,
    which propose where a far loop search looks for its best pose, and say which of several saved maps a
    drive is most like."""

    far_searches: bool = Field(True, description="Far loop closures find their best pose only around the places "
                               "the index proposes, then search the whole map for a runner-up (off: the best is "
                               "searched over the whole map; set off on open ground: "
                               "outdoors a revisit often passes metres beside the path that made the map, where "
                               "no place lies; on the campus it proposed none of the whole-map search's three "
                               "placements).")
    candidates: int = Field(5, ge=1, le=100, description="Places proposed per far search, best first.")
    window_m: float = Field(2.5, ge=0.1, le=50.0, description="Each proposed place is searched within this "
                            "distance of where it puts the vehicle [m] ...")
    window_rad: float = Field(0.25, ge=0.01, le=3.2, description="... and this turn of the heading it implies "
                              "[rad].")
    radius_m: float = Field(16.0, ge=2.0, le=100.0, description="A place describes the map's end points within "
                            "this distance [m] (recall@5 at the benchmark logs' revisits, 12 / 16 / 20 m: intel "
                            "0.93 / 0.93 / 0.90, the corridor 0.62 / 0.67 / 0.66, the campus 0.71 / 0.85 / 0.87).")
    spacing_m: float = Field(2.0, ge=0.2, le=50.0, description="Places lie this far apart: along the path that "
                             "made the map and, in a saved map, on a lattice over the free space it observed [m].")
    stretch_m: float = Field(8.0, gt=0.0, le=100.0, description="Which map: a drive is described by stretches "
                             "of this much travel [m] ...")
    stretches: int = Field(6, ge=1, le=100, description="... this many of them, spread over the drive.")

    def for_far_searches(self) -> PlaceIndexConfig | None:
        """These settings where far loop closures use the index, else None (they search the whole map)."""
        return self if self.far_searches else None


class ChangesConfig(_Section):
    """The change map of a localised or extending drive against the saved map
    (:mod:`slam_engine.multisession.changes`)."""

    enabled: bool = Field(True, description="Write the change map (changes.png, changes.geojson, run.json's "
                          "changes) of every localise and extend run.")
    resolution_m: float = Field(0.1, ge=0.02, le=1.0, description="Changes are found on cells this large [m] "
                                "(the saved map pooled to them).")
    min_scans: int = Field(3, ge=1, le=1000, description="A cell changed only where at least this many of the new "
                           "drive's scans, from poses key_spacing_m apart, agree: a person walking past is "
                           "seen by fewer.")
    key_spacing_m: float = Field(0.3, ge=0.0, le=10.0, description="The new drive's scans that count lie this far "
                                 "apart [m] (or key_spacing_rad) ...")
    key_spacing_rad: float = Field(0.2, ge=0.0, le=3.2, description="... or this turn apart [rad].")
    hit_share: float = Field(0.6, gt=0.0, le=1.0, description="An added cell: at least this share of the scans "
                             "that observed it hit it.")
    tolerance_cells: int = Field(1, ge=0, le=10, description="Neither map's obstacles within this many cells of "
                                 "a change: a localisation a few centimetres off is not a change.")
    min_region_cells: int = Field(3, ge=1, le=10000, description="Changed regions smaller than this many cells "
                                  "are left out.")


class SlamConfig(_Section):
    """Everything a run needs besides the log and the random generator."""

    particles: int = Field(30, ge=1, le=1000, description="Number of particles; with min_particles below it, "
                           "the most particles (the count a run starts with).")
    min_particles: int = Field(30, ge=1, le=1000, description="Fewest particles. Below particles, the count follows "
                               "the posterior's spread (KLD-sampling, Fox 2003) between the two; at or above "
                               "it (the default) the count is fixed. 15 runs the simulated car 0.9x the time, "
                               "but changes which seeds of the sparse logs hold (docs/engine.md).")
    kld_error: float = Field(0.5, gt=0.0, le=10.0, description="KLD-sampling's bound on the divergence between "
                             "the particles and the posterior they sample (epsilon): smaller keeps more particles.")
    kld_bin_xy_m: float = Field(0.02, gt=0.0, le=10.0, description="KLD-sampling's bin size in x and y [m].")
    kld_bin_theta_rad: float = Field(0.0087, gt=0.0, le=1.0, description="KLD-sampling's bin size in "
                                     "heading [rad].")
    seed: int = Field(0, ge=0, le=2**32 - 1, description="Seed for numpy.random.default_rng.")
    resample_threshold: float = Field(0.5, gt=0.0, le=1.0, description="Resample when N_eff < this * N.")
    grid: GridConfig = GridConfig()
    motion: MotionNoiseConfig = MotionNoiseConfig()
    heading_calibration: HeadingCalibrationConfig = HeadingCalibrationConfig()
    odometry: OdometryConfig = OdometryConfig()
    matcher: MatcherConfig = MatcherConfig()
    scheduling: SchedulingConfig = SchedulingConfig()
    loop_closing: LoopClosingConfig = LoopClosingConfig()
    localization: LocalizationConfig = LocalizationConfig()
    place_index: PlaceIndexConfig = PlaceIndexConfig()
    changes: ChangesConfig = ChangesConfig()
    lidar_filter: LidarFilterConfig = LidarFilterConfig()
    texture: TextureConfig = TextureConfig()
    snapshot_every_scans: int = Field(0, ge=0, le=100000, description="Keep a map snapshot every n "
                                      "processed scans (0 = none); used for animations.")


# The settings users set most, by one flat name (API fields, CLI options, bench flags): name -> its place
# in SlamConfig. The one table of them; every caller lays them over a config with shortcut_overrides.
SHORTCUTS: dict[str, tuple[str, ...]] = {
    "particles": ("particles",),
    "seed": ("seed",),
    "resolution_m": ("grid", "resolution_m"),
    "max_range_m": ("grid", "max_range_m"),
    "linear_update_m": ("scheduling", "linear_update_m"),
    "angular_update_rad": ("scheduling", "angular_update_rad"),
    "snapshot_every_scans": ("snapshot_every_scans",),
}


def shortcut_overrides(values: Mapping[str, Any]) -> dict[str, Any]:
    """Nested settings from flat :data:`SHORTCUTS` values (``{"resolution_m": 0.1}`` ->
    ``{"grid": {"resolution_m": 0.1}}``); None values are left out. Other names raise KeyError."""
    nested: dict[str, Any] = {}
    for name, value in values.items():
        if value is None:
            continue
        *sections, key = SHORTCUTS[name]
        place = nested
        for section in sections:
            place = place.setdefault(section, {})
        place[key] = value
    return nested


def shortcut_values(config: SlamConfig) -> dict[str, Any]:
    """The :data:`SHORTCUTS` settings of ``config``, by their flat names."""
    values = {}
    for name, path in SHORTCUTS.items():
        value: Any = config
        for key in path:
            value = getattr(value, key)
        values[name] = value
    return values


def merge_settings(base: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``overrides`` laid over it; nested sections (dicts) merge key by key."""
    merged = dict(base)
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = merge_settings(merged[key], value)
        else:
            merged[key] = value
    return merged


def validate_config(settings: Mapping[str, Any], where: str = "config") -> SlamConfig:
    """A SlamConfig from nested settings; raises ConfigError listing every bad field
    (``where: bad config: grid.resolution_m: Input should be ...``)."""
    try:
        return SlamConfig.model_validate(dict(settings))
    except ValidationError as error:
        details = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in error.errors())
        raise ConfigError(f"{where}: bad config: {details}") from None


def read_settings(path: str | Path) -> dict[str, Any]:
    """The settings mapping in a YAML or JSON file (empty file: no settings); ConfigError naming the
    file and line when it is not YAML/JSON or not a mapping."""
    import yaml

    try:
        loaded = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f", line {mark.line + 1}" if mark is not None else ""
        problem = getattr(error, "problem", None) or str(error)
        raise ConfigError(f"{path}{where}: not valid YAML or JSON: {problem}") from None
    if loaded is None:
        return {}
    if not isinstance(loaded, dict):
        raise ConfigError(f"{path}: a config file holds a mapping of settings, not {type(loaded).__name__}")
    return loaded


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> SlamConfig:
    """SlamConfig from a YAML/JSON file (or the defaults), with ``overrides`` merged over it
    (``{"grid": {"resolution_m": 0.1}}`` changes that one setting); validated."""
    settings = read_settings(path) if path is not None else {}
    settings = merge_settings(settings, overrides or {})
    return validate_config(settings, str(path) if path is not None else "settings")


def defaults_yaml() -> str:
    """The default configuration as YAML, every setting with its description, bounds and units as a
    comment (what ``lidarmap config`` prints; a valid config file as it stands)."""
    lines = ["# lidarmap SlamConfig: the defaults. Copy, edit, and pass with --config (YAML or JSON)."]
    _describe(SlamConfig, SlamConfig(), lines, indent="")
    return "\n".join(lines) + "\n"


def _describe(model: type[BaseModel], value: BaseModel, lines: list[str], indent: str) -> None:
    for name, info in model.model_fields.items():
        current = getattr(value, name)
        if isinstance(current, BaseModel):
            doc = (type(current).__doc__ or "").split("\n\n")[0]
            lines.append("")
            lines.append(f"{indent}{name}:  # {' '.join(doc.split())}")
            _describe(type(current), current, lines, indent + "  ")
            continue
        bounds = [f"{op} {getattr(m, attr)}" for m in info.metadata
                  for attr, op in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<"), ("multiple_of", "x"))
                  if getattr(m, attr, None) is not None]
        note = " ".join((info.description or "").split())
        if bounds:
            note += f" ({', '.join(bounds)})"
        lines.append(f"{indent}{name}: {json.dumps(current)}  # {note}")
