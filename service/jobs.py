"""Job and asset records and the stores that keep them: one import for callers.

The pieces live in service.models (records), service.store (the JobStore
protocol), service.redis_store (distributed mode) and service.sqlite_store
(embedded mode).
"""

from __future__ import annotations

from service.models import (  # noqa: F401
    TERMINAL,
    Artifact,
    Asset,
    InputRef,
    Job,
    JobState,
    new_id,
)
from service.redis_store import RedisJobStore  # noqa: F401
from service.sqlite_store import SQLiteJobStore  # noqa: F401
from service.store import JobStore  # noqa: F401
