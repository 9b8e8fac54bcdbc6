"""Job and asset records and the two stores behind one interface.

RedisJobStore (distributed mode) keeps each job as a Redis hash whose fields
are JSON values; state changes go through one Lua compare-and-set script so the
API (cancel), workers (progress, completion) and reapers (lost workers) never
overwrite each other. SQLiteJobStore (embedded mode) does the same inside
`BEGIN IMMEDIATE` transactions and survives API restarts.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
import uuid
from enum import Enum
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field


class JobState(str, Enum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"


TERMINAL = {JobState.succeeded, JobState.failed, JobState.cancelled}


class InputRef(BaseModel):
    asset_id: str
    key: str
    kind: str  # "ply" | "images"
    filename: str | None = None


class Artifact(BaseModel):
    name: str
    key: str
    size: int
    content_type: str


class Job(BaseModel):
    id: str
    owner: str
    state: JobState = JobState.queued
    stage: str | None = None
    progress: float = 0.0
    created_at: float
    updated_at: float
    started_at: float | None = None
    finished_at: float | None = None
    attempts: int = 0
    max_attempts: int = 3
    sources: list[InputRef]
    target: InputRef
    options: dict[str, Any] = Field(default_factory=dict)
    webhook: dict[str, Any] | None = None
    idempotency_key: str | None = None
    error: dict[str, Any] | None = None
    result: dict[str, Any] | None = None
    artifacts: list[Artifact] = Field(default_factory=list)
    cancel_requested: bool = False
    run_token: str | None = None
    lease_until: float | None = None
    worker: str | None = None
    # The queue's own handle (RQ job id) and when it was last enqueued: lets the
    # reaper notice a queue message lost before any worker claimed the job.
    queue_ref: str | None = None
    enqueued_at: float | None = None
    version: int = 0

    @property
    def terminal(self) -> bool:
        return self.state in TERMINAL


class Asset(BaseModel):
    id: str
    owner: str
    kind: str
    key: str
    size: int
    filename: str | None = None
    content_type: str
    n_gaussians: int | None = None
    n_images: int | None = None
    sha256: str
    created_at: float


def new_id(prefix: str) -> str:
    return f"{prefix}_{uuid.uuid4().hex}"


def _enc(v: Any) -> str:
    if isinstance(v, BaseModel):
        return v.model_dump_json()
    if isinstance(v, list):
        return json.dumps(
            [x.model_dump(mode="json") if isinstance(x, BaseModel) else x for x in v]
        )
    if isinstance(v, Enum):
        return json.dumps(v.value)
    return json.dumps(v)


class JobStore:
    """Interface; see RedisJobStore and SQLiteJobStore."""

    def create(self, job: Job) -> None: ...
    def get(self, job_id: str) -> Job | None: ...

    def update(
        self,
        job_id: str,
        *,
        states: set[JobState] | None = None,
        token: str | None = None,
        **fields,
    ) -> bool:
        """Set fields iff the job is in one of `states` (any if None) and, if given, holds run_token `token`."""

    def list(
        self,
        owner: str,
        state: JobState | None,
        limit: int,
        cursor: tuple[float, str] | None,
    ) -> list[Job]: ...
    def running(self) -> list[Job]: ...
    def queued_ids(self) -> list[str]: ...
    def counts(self) -> dict[str, int]: ...
    def claim_idempotency(
        self, owner: str, key: str, body_hash: str, job_id: str
    ) -> tuple[str, str] | None: ...
    def release_idempotency(self, owner: str, key: str) -> None: ...
    def put_asset(self, asset: Asset) -> None: ...
    def delete_asset(self, asset_id: str) -> None: ...
    def get_asset(self, asset_id: str) -> Asset | None: ...
    def record_stage(self, stage: str, seconds: float) -> None: ...
    def stage_stats(self) -> dict[str, tuple[int, float]]: ...
    def ping(self) -> bool: ...


_CAS = """
local st = redis.call('HGET', KEYS[1], 'state')
if not st then return 0 end
if ARGV[1] ~= '' then
  local ok = false
  for s in string.gmatch(ARGV[1], '[^,]+') do if s == st then ok = true end end
  if not ok then return 0 end
end
if ARGV[2] ~= '' and redis.call('HGET', KEYS[1], 'run_token') ~= ARGV[2] then return 0 end
local newst = nil
for i = 3, #ARGV, 2 do
  redis.call('HSET', KEYS[1], ARGV[i], ARGV[i+1])
  if ARGV[i] == 'state' then newst = ARGV[i+1] end
end
redis.call('HINCRBY', KEYS[1], 'version', 1)
if newst and newst ~= st then
  local id = string.sub(KEYS[1], string.len(KEYS[2]) + 1)
  redis.call('SREM', KEYS[3] .. st, id)
  redis.call('SADD', KEYS[3] .. newst, id)
end
return 1
"""


class RedisJobStore(JobStore):
    def __init__(self, redis_client, prefix: str = "gsa:"):
        self.r = redis_client
        self.p = prefix
        self._cas = self.r.register_script(_CAS)

    def _jk(self, job_id):
        return f"{self.p}job:{job_id}"

    def create(self, job: Job) -> None:
        data = {k: _enc(getattr(job, k)) for k in Job.model_fields}
        pipe = self.r.pipeline(transaction=True)
        pipe.hset(self._jk(job.id), mapping=data)
        pipe.zadd(f"{self.p}owner:{job.owner}", {job.id: job.created_at})
        pipe.sadd(f"{self.p}state:{_enc(job.state)}", job.id)
        pipe.execute()

    def _decode(self, raw: dict) -> Job | None:
        if not raw:
            return None
        d = {k.decode(): json.loads(v) for k, v in raw.items()}
        return Job.model_validate(d)

    def get(self, job_id: str) -> Job | None:
        return self._decode(self.r.hgetall(self._jk(job_id)))

    def update(self, job_id, *, states=None, token=None, **fields) -> bool:
        fields.setdefault("updated_at", time.time())
        argv = [
            ",".join(_enc(s) for s in states) if states else "",
            _enc(token) if token else "",
        ]
        for k, v in fields.items():
            argv += [k, _enc(v)]
        keys = [self._jk(job_id), f"{self.p}job:", f"{self.p}state:"]
        return bool(self._cas(keys=keys, args=argv))

    def _many(self, ids) -> list[Job]:
        pipe = self.r.pipeline(transaction=False)
        for i in ids:
            pipe.hgetall(self._jk(i.decode() if isinstance(i, bytes) else i))
        return [j for j in map(self._decode, pipe.execute()) if j is not None]

    def list(self, owner, state, limit, cursor):
        key = f"{self.p}owner:{owner}"
        out: list[Job] = []
        top = "+inf" if cursor is None else cursor[0]
        offset = 0
        while len(out) < limit:
            batch = self.r.zrevrangebyscore(
                key, top, "-inf", start=offset, num=200, withscores=True
            )
            if not batch:
                break
            offset += len(batch)
            ids = []
            for raw_id, score in batch:
                jid = raw_id.decode()
                # Ties in created_at: zrevrange orders equal scores by id descending.
                if cursor is not None and score == cursor[0] and jid >= cursor[1]:
                    continue
                ids.append(jid)
            for job in self._many(ids):
                if state is None or job.state == state:
                    out.append(job)
                    if len(out) == limit:
                        break
        return out

    def running(self):
        return self._many(self.r.smembers(f"{self.p}state:{_enc(JobState.running)}"))

    def queued_ids(self):
        return [
            i.decode()
            for i in self.r.smembers(f"{self.p}state:{_enc(JobState.queued)}")
        ]

    def counts(self):
        pipe = self.r.pipeline(transaction=False)
        for s in JobState:
            pipe.scard(f"{self.p}state:{_enc(s)}")
        return {s.value: int(n) for s, n in zip(JobState, pipe.execute())}

    def claim_idempotency(self, owner, key, body_hash, job_id):
        k = f"{self.p}idem:{owner}:{key}"
        if self.r.set(k, f"{job_id}|{body_hash}", nx=True, ex=24 * 3600):
            return None
        job, _, h = self.r.get(k).decode().partition("|")
        return job, h

    def release_idempotency(self, owner, key):
        self.r.delete(f"{self.p}idem:{owner}:{key}")

    def delete_asset(self, asset_id):
        self.r.delete(f"{self.p}asset:{asset_id}")

    def put_asset(self, asset):
        self.r.set(f"{self.p}asset:{asset.id}", asset.model_dump_json())

    def get_asset(self, asset_id):
        raw = self.r.get(f"{self.p}asset:{asset_id}")
        return Asset.model_validate_json(raw) if raw else None

    def record_stage(self, stage, seconds):
        pipe = self.r.pipeline(transaction=False)
        pipe.hincrby(f"{self.p}stage_count", stage, 1)
        pipe.hincrbyfloat(f"{self.p}stage_seconds", stage, seconds)
        pipe.execute()

    def stage_stats(self):
        counts = self.r.hgetall(f"{self.p}stage_count")
        secs = self.r.hgetall(f"{self.p}stage_seconds")
        return {k.decode(): (int(v), float(secs.get(k, 0))) for k, v in counts.items()}

    def ping(self):
        try:
            return bool(self.r.ping())
        except Exception:
            return False


class SQLiteJobStore(JobStore):
    """Embedded mode: one process owns the file; a lock serialises writers."""

    def __init__(self, path: str | Path):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.db = sqlite3.connect(
            str(path), check_same_thread=False, isolation_level=None, timeout=30
        )
        self.lock = threading.RLock()
        with self.lock:
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=NORMAL")
            self.db.executescript(
                """
                CREATE TABLE IF NOT EXISTS jobs (id TEXT PRIMARY KEY, owner TEXT, state TEXT,
                    created_at REAL, data TEXT);
                CREATE INDEX IF NOT EXISTS jobs_owner ON jobs(owner, created_at DESC, id DESC);
                CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state);
                CREATE TABLE IF NOT EXISTS assets (id TEXT PRIMARY KEY, data TEXT);
                CREATE TABLE IF NOT EXISTS idem (k TEXT PRIMARY KEY, job_id TEXT, hash TEXT, at REAL);
                CREATE TABLE IF NOT EXISTS stages (stage TEXT PRIMARY KEY, n INTEGER, secs REAL);
                """
            )

    def create(self, job):
        with self.lock:
            self.db.execute(
                "INSERT INTO jobs VALUES (?,?,?,?,?)",
                (
                    job.id,
                    job.owner,
                    job.state.value,
                    job.created_at,
                    job.model_dump_json(),
                ),
            )

    def get(self, job_id):
        with self.lock:
            row = self.db.execute(
                "SELECT data FROM jobs WHERE id=?", (job_id,)
            ).fetchone()
        return Job.model_validate_json(row[0]) if row else None

    def update(self, job_id, *, states=None, token=None, **fields):
        fields.setdefault("updated_at", time.time())
        with self.lock:
            self.db.execute("BEGIN IMMEDIATE")
            try:
                row = self.db.execute(
                    "SELECT data FROM jobs WHERE id=?", (job_id,)
                ).fetchone()
                if row is None:
                    self.db.execute("ROLLBACK")
                    return False
                job = Job.model_validate_json(row[0])
                if (states and job.state not in states) or (
                    token and job.run_token != token
                ):
                    self.db.execute("ROLLBACK")
                    return False
                job = job.model_validate(
                    {**job.model_dump(), **fields, "version": job.version + 1}
                )
                self.db.execute(
                    "UPDATE jobs SET state=?, data=? WHERE id=?",
                    (job.state.value, job.model_dump_json(), job_id),
                )
                self.db.execute("COMMIT")
                return True
            except BaseException:
                self.db.execute("ROLLBACK")
                raise

    def list(self, owner, state, limit, cursor):
        q, args = "SELECT data FROM jobs WHERE owner=?", [owner]
        if state is not None:
            q += " AND state=?"
            args.append(state.value)
        if cursor is not None:
            q += " AND (created_at < ? OR (created_at = ? AND id < ?))"
            args += [cursor[0], cursor[0], cursor[1]]
        q += " ORDER BY created_at DESC, id DESC LIMIT ?"
        args.append(limit)
        with self.lock:
            rows = self.db.execute(q, args).fetchall()
        return [Job.model_validate_json(r[0]) for r in rows]

    def running(self):
        with self.lock:
            rows = self.db.execute(
                "SELECT data FROM jobs WHERE state='running'"
            ).fetchall()
        return [Job.model_validate_json(r[0]) for r in rows]

    def queued_ids(self):
        with self.lock:
            rows = self.db.execute(
                "SELECT id FROM jobs WHERE state='queued' ORDER BY created_at"
            ).fetchall()
        return [r[0] for r in rows]

    def counts(self):
        with self.lock:
            rows = dict(
                self.db.execute(
                    "SELECT state, COUNT(*) FROM jobs GROUP BY state"
                ).fetchall()
            )
        return {s.value: int(rows.get(s.value, 0)) for s in JobState}

    def claim_idempotency(self, owner, key, body_hash, job_id):
        k = f"{owner}:{key}"
        with self.lock:
            cur = self.db.execute(
                "INSERT OR IGNORE INTO idem VALUES (?,?,?,?)",
                (k, job_id, body_hash, time.time()),
            )
            if cur.rowcount == 1:
                return None
            row = self.db.execute(
                "SELECT job_id, hash FROM idem WHERE k=?", (k,)
            ).fetchone()
        return row[0], row[1]

    def release_idempotency(self, owner, key):
        with self.lock:
            self.db.execute("DELETE FROM idem WHERE k=?", (f"{owner}:{key}",))

    def delete_asset(self, asset_id):
        with self.lock:
            self.db.execute("DELETE FROM assets WHERE id=?", (asset_id,))

    def put_asset(self, asset):
        with self.lock:
            self.db.execute(
                "INSERT OR REPLACE INTO assets VALUES (?,?)",
                (asset.id, asset.model_dump_json()),
            )

    def get_asset(self, asset_id):
        with self.lock:
            row = self.db.execute(
                "SELECT data FROM assets WHERE id=?", (asset_id,)
            ).fetchone()
        return Asset.model_validate_json(row[0]) if row else None

    def record_stage(self, stage, seconds):
        with self.lock:
            self.db.execute(
                "INSERT INTO stages VALUES (?,1,?) ON CONFLICT(stage) DO UPDATE SET n=n+1, secs=secs+excluded.secs",
                (stage, seconds),
            )

    def stage_stats(self):
        with self.lock:
            return {
                s: (n, secs)
                for s, n, secs in self.db.execute("SELECT stage, n, secs FROM stages")
            }

    def ping(self):
        try:
            with self.lock:
                self.db.execute("SELECT 1")
            return True
        except Exception:
            return False
