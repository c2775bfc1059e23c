"""Mapping jobs: a SLAM run over a session's log or stream, with its progress and products."""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

LOADING_MAP_STAGE = "loading the map"  # a live localisation's stage until it is ready for the stream


class JobStatus(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


class JobSource(StrEnum):
    LOG = "log"  # an uploaded log (the newest one unless log_id is given)
    STREAM = "stream"  # the streamed chunks 0..k received when the job starts (or, live, as they arrive)
    MAP = "map"  # an uploaded map bundle (POST /v1/sessions/{id}/maps): a finished job whose product it is


class JobMode(StrEnum):
    MAP = "map"  # build a map of the input
    LOCALIZE = "localize"  # place the input in the map of map_job_id (the map does not change)
    EXTEND = "extend"  # map the input, place it in the map of map_job_id and make one map of both
    MERGE = "merge"  # make one map of the saved maps of map_job_id and merge_job_id (no input to map)


class JobCreate(BaseModel):
    """A job: what to map, and the engine settings (a SlamConfig: ``lidarmap config`` lists every one with
    its default, units and bounds). The service validates the settings with the engine's own bounds
    (422 naming the setting), so every run's cost is finite."""

    model_config = ConfigDict(extra="forbid")

    source: JobSource | None = Field(None, description="Default: 'log' if the session has an upload, "
                                     "else 'stream'.")
    log_id: str | None = Field(None, max_length=64, description="Which upload (default: the newest).")
    slam: dict[str, Any] = Field(default_factory=dict, description="Engine settings, nested by section as "
                                 "SlamConfig has them, any subset, e.g. {\"grid\": {\"no_return_clear_m\": 4.0}, "
                                 "\"matcher\": {\"search_xy_m\": 0.5}}; the rest keep their defaults.")
    # Shortcuts for the settings most runs change; each overrides its slam.* counterpart.
    particles: int | None = Field(None, strict=True, description="= slam.particles (default 30); with "
                                  "slam.min_particles below it, the most particles.")
    seed: int | None = Field(None, strict=True, description="= slam.seed (default 0).")
    resolution_m: float | None = Field(None, strict=True, description="= slam.grid.resolution_m: grid cell size [m] "
                                       "(default 0.05).")
    max_range_m: float | None = Field(None, strict=True,
                                      description="= slam.grid.max_range_m: beams are used up to this "
                                      "range [m] (default 30).")
    linear_update_m: float | None = Field(None, strict=True, description="= slam.scheduling.linear_update_m: process a "
                                          "scan after this much travel [m] (default 0.2).")
    angular_update_rad: float | None = Field(None, strict=True,
                                             description="= slam.scheduling.angular_update_rad: ... or "
                                             "this much rotation [rad] (default 0.1).")
    snapshot_every_scans: int | None = Field(None, strict=True,
                                             description="= slam.snapshot_every_scans: live map preview "
                                             "and animation frame every n processed scans (0 = none; default "
                                             "for a job 50).")
    live: bool = Field(False, description="Follow the session's stream: map chunks in seq order as they "
                       "arrive (a gap waits for its chunk) until the stream is finished "
                       "(POST /v1/sessions/{id}/chunks/finish) or idle for idle_timeout_s. One live job per "
                       "session at a time; it holds a worker while it waits. With 'mode': 'localize' it "
                       "localises the stream in map_job_id's saved map scan by scan instead: each scan's pose, "
                       "confidence and state at GET /v1/jobs/{id}/poses (server-sent events with stream=true).")
    mode: JobMode = Field(JobMode.MAP, description="'map' the input; 'localize' it in the saved map of "
                          "map_job_id (its trajectory in that map's frame; refused, the job failing with the best "
                          "score, when it is not in the map); 'extend' that map with it (one map of both drives, "
                          "loops between them closed). Products of a localisation: trajectory, confidence.json, "
                          "localization.png, run.json.")
    map_job_id: str | None = Field(None, max_length=64, description="The finished job (a mapping or "
                                   "extension job, or an uploaded map) whose map_bundle.npz the job starts from: "
                                   "required for 'extend'; a 'localize' job without it searches every saved map "
                                   "of the key (the newest 50) and localises the drive in the one it is in "
                                   "(run.json: localization.which_map).")
    merge_job_id: str | None = Field(None, max_length=64, description="'merge': the second saved map (a "
                                     "finished job, as map_job_id), merged into the map of map_job_id, whose "
                                     "frame the merged map keeps. Refused (the job failing) when they do not "
                                     "overlap.")
    idle_timeout_s: float = Field(600.0, strict=True,
                                  ge=1.0, le=86_400.0, description="Live jobs: with no new chunk to map "
                                  "for this long [s], the job ends and writes the products of what it mapped "
                                  "(fails when it mapped nothing).")

    @model_validator(mode="after")
    def _live_follows_a_stream(self) -> JobCreate:
        if self.source is JobSource.MAP and self.mode is not JobMode.MERGE:
            raise ValueError("a job maps a 'log' or a 'stream'; an uploaded map is POSTed to "
                             "/v1/sessions/{id}/maps and named as 'map_job_id'")
        if self.live and (self.source is JobSource.LOG or self.log_id is not None):
            raise ValueError("a live job follows the session's stream: leave 'source' out (or 'stream') "
                             "and give no 'log_id'")
        if self.mode is JobMode.MAP and self.map_job_id is not None:
            raise ValueError("'map_job_id' names the saved map that 'localize' and 'extend' start from: give it "
                             "with those modes, and only with them")
        if self.mode is JobMode.EXTEND and self.map_job_id is None:
            raise ValueError("'extend' grows the saved map of 'map_job_id': name it")
        if (self.mode is JobMode.MERGE) != (self.merge_job_id is not None):
            raise ValueError("'merge_job_id' names the second map of a 'merge': give it with that mode, and only "
                             "with it")
        if self.mode is JobMode.MERGE and (self.map_job_id is None or self.source not in (None, JobSource.MAP)
                                           or self.log_id is not None or self.live):
            raise ValueError("a 'merge' joins two saved maps, 'map_job_id' and 'merge_job_id': it maps no log "
                             "or stream")
        if self.live and self.mode not in (JobMode.MAP, JobMode.LOCALIZE):
            raise ValueError("a live job maps its stream ('mode': 'map') or localises it in a saved map "
                             "('mode': 'localize'); extend with the finished stream instead")
        if self.live and self.mode is JobMode.LOCALIZE and self.map_job_id is None:
            raise ValueError("a live localisation follows the stream in one saved map: name it as 'map_job_id'")
        return self


class JobPublic(BaseModel):
    id: str
    session_id: str
    source: JobSource
    log_id: str | None
    status: JobStatus
    mode: JobMode = Field(JobMode.MAP, description="'map', 'localize' or 'extend' (the job's setting).")
    map_job_id: str | None = Field(None, description="The saved map's job for 'localize' and 'extend'.")
    merge_job_id: str | None = Field(None, description="The second saved map's job of a 'merge'.")
    live: bool = Field(False, description="A live job: it follows the session's stream.")
    particles: int | None = Field(None, description="The engine's particle count (= config.slam.particles).")
    stage: str | None = Field(None, description="While running: what the job does now - 'mapping scans', "
                              "'closing loops', 'aligning to the map', 'rendering the map', 'writing products', "
                              "in that order ('loading the map' then 'localising scans' for a live localisation: it is "
                              "ready for the stream once it localises; null when not running or not yet known).")
    progress: float | None = Field(ge=0.0, le=1.0, description="The job's share done, 0..1, over every stage "
                                   "(each weighted by its usual share of a run's time: mapping the scans is about "
                                   "70 %); 1.0 once it succeeded. Null for a live job until it succeeds (its total "
                                   "is unknown while the stream goes on).")
    scans_done: int
    scans_total: int | None = Field(description="Scans in the input; null while unknown (before the run "
                                    "starts, and for a live job until it succeeds).")
    eta_s: float | None = Field(description="Estimated seconds left while running, from the share done so "
                                "far (null while unknown, e.g. while the engine compiles).")
    compiling: bool = Field(False, description="The engine is compiling its kernels (the first job after an "
                            "install whose kernel cache is not warm, about 30 s): no scans are mapped meanwhile.")
    error: str | None = Field(description="Why the job failed or was cancelled.")
    cancel_requested: bool
    config: dict[str, Any] | None = Field(None, description="The job's settings: 'slam' is the whole engine "
                                          "configuration it runs with (a SlamConfig); the shortcut fields repeat "
                                          "its values. Given when the job is created, and with ?include=config "
                                          "(GET /v1/jobs/{id}, GET /v1/jobs); null otherwise, to keep polls small.")
    input: dict[str, Any] | None = Field(description="What the job mapped (log summary; chunks used).")
    products: list[str] = Field(description="Product names available now, e.g. 'occupancy.png'.")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobsPublic(BaseModel):
    data: list[JobPublic]
    count: int
