"""The job store of distributed mode: Redis.

Each job is a Redis hash whose fields are JSON values; state changes go through
one Lua compare-and-set script (_CAS) so the API (cancel), workers (progress,
completion) and reapers (lost workers) never overwrite each other.
"""

from __future__ import annotations

import json
import time
from enum import Enum
from typing import Any

from pydantic import BaseModel

from service.models import Asset, Job, JobState
from service.stores.base import IDEM_PENDING_S, IDEM_TTL_S


def _enc(v: Any) -> str:
    if isinstance(v, BaseModel):
        return v.model_dump_json()
    if isinstance(v, list):
        return json.dumps([x.model_dump(mode="json") if isinstance(x, BaseModel) else x for x in v])
    if isinstance(v, Enum):
        return json.dumps(v.value)
    return json.dumps(v)


# KEYS: the job's hash, the job-key prefix, the state-set prefix.
# ARGV: allowed states ("a,b" or ""), required run_token ("" = any), then field/value pairs.
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


# Per-owner storage ledger (service.jobs.quotas). KEYS: the owner's item hash, its total.
# ARGV: item, bytes. The total moves by the difference, so setting an item twice counts it once.
_USAGE_SET = """
local old = tonumber(redis.call('HGET', KEYS[1], ARGV[1]) or '0')
redis.call('HSET', KEYS[1], ARGV[1], ARGV[2])
return redis.call('INCRBY', KEYS[2], tonumber(ARGV[2]) - old)
"""
_USAGE_DROP = """
local old = redis.call('HGET', KEYS[1], ARGV[1])
if not old then return tonumber(redis.call('GET', KEYS[2]) or '0') end
redis.call('HDEL', KEYS[1], ARGV[1])
return redis.call('INCRBY', KEYS[2], -tonumber(old))
"""


class RedisJobStore:
    """Distributed mode: one Redis hash per job, JSON field values."""

    def __init__(self, redis_client, prefix: str = "gsa:"):
        self.r = redis_client
        self.p = prefix
        self._cas = self.r.register_script(_CAS)
        self._usage_set = self.r.register_script(_USAGE_SET)
        self._usage_drop = self.r.register_script(_USAGE_DROP)

    def _jk(self, job_id):
        return f"{self.p}job:{job_id}"

    def create(self, job: Job) -> None:
        data = {k: _enc(getattr(job, k)) for k in Job.model_fields}
        pipe = self.r.pipeline(transaction=True)
        pipe.hset(self._jk(job.id), mapping=data)
        pipe.zadd(f"{self.p}owner:{job.owner}", {job.id: job.created_at})
        pipe.sadd(f"{self.p}state:{_enc(job.state)}", job.id)
        if job.idempotency_key:  # the claim made for this job now lasts its full time
            pipe.expire(f"{self.p}idem:{job.owner}:{job.idempotency_key}", IDEM_TTL_S)
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
            batch = self.r.zrevrangebyscore(key, top, "-inf", start=offset, num=200, withscores=True)
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
        return [i.decode() for i in self.r.smembers(f"{self.p}state:{_enc(JobState.queued)}")]

    def counts(self):
        pipe = self.r.pipeline(transaction=False)
        for s in JobState:
            pipe.scard(f"{self.p}state:{_enc(s)}")
        return {s.value: int(n) for s, n in zip(JobState, pipe.execute())}

    def claim_idempotency(self, owner, key, body_hash, job_id):
        k = f"{self.p}idem:{owner}:{key}"
        if self.r.set(k, f"{job_id}|{body_hash}", nx=True, ex=IDEM_PENDING_S):
            return None
        job, _, h = self.r.get(k).decode().partition("|")
        return job, h

    def release_idempotency(self, owner, key):
        self.r.delete(f"{self.p}idem:{owner}:{key}")

    def delete(self, job_id):
        job = self.get(job_id)
        if job is None:
            return False
        pipe = self.r.pipeline(transaction=True)
        pipe.delete(self._jk(job_id))
        pipe.zrem(f"{self.p}owner:{job.owner}", job_id)
        for s in JobState:
            pipe.srem(f"{self.p}state:{_enc(s)}", job_id)
        pipe.execute()
        if job.idempotency_key:
            k = f"{self.p}idem:{job.owner}:{job.idempotency_key}"
            held = self.r.get(k)
            if held is not None and held.decode().partition("|")[0] == job_id:
                self.r.delete(k)
        return True

    def jobs(self):
        pipe = self.r.pipeline(transaction=False)
        for s in JobState:
            pipe.smembers(f"{self.p}state:{_enc(s)}")
        ids = sorted({i for members in pipe.execute() for i in members})
        for start in range(0, len(ids), 500):
            yield from self._many(ids[start : start + 500])

    def asset_ids(self):
        n = len(f"{self.p}asset:")
        return [k.decode()[n:] for k in self.r.scan_iter(match=f"{self.p}asset:*", count=1000)]

    def add_blob_ref(self, key, asset_id):
        pipe = self.r.pipeline(transaction=True)
        pipe.sadd(f"{self.p}blobrefs:{key}", asset_id)
        pipe.scard(f"{self.p}blobrefs:{key}")
        return int(pipe.execute()[1])

    def remove_blob_ref(self, key, asset_id):
        pipe = self.r.pipeline(transaction=True)
        pipe.srem(f"{self.p}blobrefs:{key}", asset_id)
        pipe.scard(f"{self.p}blobrefs:{key}")
        return int(pipe.execute()[1])

    def blob_lock(self, key):
        # Held for one Redis round trip and a storage check (seconds at worst); expires if its holder dies.
        return self.r.lock(f"{self.p}blobrefs-lock:{key}", timeout=60, blocking_timeout=30)

    def blob_ref_ids(self, key):
        return sorted(i.decode() for i in self.r.smembers(f"{self.p}blobrefs:{key}"))

    def delete_asset(self, asset_id):
        asset = self.get_asset(asset_id)
        pipe = self.r.pipeline(transaction=True)
        pipe.delete(f"{self.p}asset:{asset_id}")
        if asset is not None:
            pipe.zrem(f"{self.p}owner-assets:{asset.owner}", asset_id)
        pipe.execute()

    def put_asset(self, asset):
        pipe = self.r.pipeline(transaction=True)
        pipe.set(f"{self.p}asset:{asset.id}", asset.model_dump_json())
        pipe.zadd(f"{self.p}owner-assets:{asset.owner}", {asset.id: asset.created_at})
        pipe.execute()

    def _index_assets(self) -> None:
        """Assets stored before the per-owner index existed join it, once per database (a
        second pass, from another process at the same time, only adds what is there again)."""
        done = f"{self.p}owner-assets-indexed"
        if self.r.exists(done):
            return
        ids = self.asset_ids()
        for start in range(0, len(ids), 500):
            chunk = ids[start : start + 500]
            pipe = self.r.pipeline(transaction=False)
            for raw in self.r.mget([f"{self.p}asset:{i}" for i in chunk]):
                if raw:
                    a = Asset.model_validate_json(raw)
                    pipe.zadd(f"{self.p}owner-assets:{a.owner}", {a.id: a.created_at})
            pipe.execute()
        self.r.set(done, "1")

    def list_assets(self, owner, limit, cursor):
        self._index_assets()
        key = f"{self.p}owner-assets:{owner}"
        out: list[Asset] = []
        top = "+inf" if cursor is None else cursor[0]
        offset = 0
        while len(out) < limit:
            batch = self.r.zrevrangebyscore(key, top, "-inf", start=offset, num=200, withscores=True)
            if not batch:
                break
            offset += len(batch)
            # Ties in created_at: zrevrange orders equal scores by id descending.
            ids = [i.decode() for i, score in batch if cursor is None or score < cursor[0] or i.decode() < cursor[1]]
            raws = self.r.mget([f"{self.p}asset:{i}" for i in ids]) if ids else []
            gone = [i for i, raw in zip(ids, raws) if raw is None]
            if gone:  # deleted while the index was being filled: drop the stale entries
                self.r.zrem(key, *gone)
            for raw in raws:
                if raw is not None:
                    out.append(Asset.model_validate_json(raw))
                    if len(out) == limit:
                        break
        return out

    def get_asset(self, asset_id):
        raw = self.r.get(f"{self.p}asset:{asset_id}")
        return Asset.model_validate_json(raw) if raw else None

    def active_jobs(self, owner):
        # The owner's job index intersected with the queued and running state sets (Redis >= 7).
        pipe = self.r.pipeline(transaction=False)
        for s in (JobState.queued, JobState.running):
            pipe.zintercard(2, [f"{self.p}owner:{owner}", f"{self.p}state:{_enc(s)}"])
        return sum(int(n) for n in pipe.execute())

    def _usage_keys(self, owner):
        return [f"{self.p}usage:{owner}", f"{self.p}usage-total:{owner}"]

    def set_usage(self, owner, item, nbytes):
        return int(self._usage_set(keys=self._usage_keys(owner), args=[item, int(nbytes)]))

    def drop_usage(self, owner, item):
        return int(self._usage_drop(keys=self._usage_keys(owner), args=[item]))

    def usage(self, owner):
        return int(self.r.get(self._usage_keys(owner)[1]) or 0)

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
        from redis.exceptions import RedisError  # loaded with the client that made self.r

        try:
            return bool(self.r.ping())
        except RedisError:
            return False
