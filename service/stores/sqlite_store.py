"""The job store of embedded mode: SQLite.

Compare-and-set updates run inside `BEGIN IMMEDIATE` transactions; the file
survives API restarts.
"""

from __future__ import annotations

import os
import sqlite3
import threading
import time
from pathlib import Path

from service.models import Asset, Job, JobState
from service.stores.base import IDEM_PENDING_S, IDEM_TTL_S

RESERVE_BYTES = 4 << 20
RESERVE_SLICE = 256 << 10  # given up at a time for a write on a full disk


def _disk_full(exc: BaseException) -> bool:
    return isinstance(exc, sqlite3.OperationalError) and "full" in str(exc).lower()


class SQLiteJobStore:
    """Embedded mode: one process owns the file; a lock serialises writers."""

    def __init__(self, path: str | Path, reserve_bytes: int = RESERVE_BYTES):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        # Room kept on the database's disk for deletes: on a full disk SQLite cannot even
        # append a DELETE to its write-ahead log, so the API could not free the space it needs.
        self.reserve, self.reserve_bytes = Path(str(path) + ".reserve"), reserve_bytes
        self._ensure_reserve()
        self.db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None, timeout=30)
        self.lock = threading.RLock()
        self._blob_lock = threading.Lock()
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
                CREATE INDEX IF NOT EXISTS assets_owner ON assets(json_extract(data, '$.owner'),
                    json_extract(data, '$.created_at') DESC, id DESC);
                CREATE TABLE IF NOT EXISTS idem (k TEXT PRIMARY KEY, job_id TEXT, hash TEXT, at REAL);
                CREATE TABLE IF NOT EXISTS stages (stage TEXT PRIMARY KEY, n INTEGER, secs REAL);
                CREATE TABLE IF NOT EXISTS blobrefs (k TEXT, asset_id TEXT, PRIMARY KEY (k, asset_id));
                CREATE TABLE IF NOT EXISTS usage (owner TEXT, item TEXT, bytes INTEGER,
                    PRIMARY KEY (owner, item));
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
            row = self.db.execute("SELECT data FROM jobs WHERE id=?", (job_id,)).fetchone()
        return Job.model_validate_json(row[0]) if row else None

    def update(self, job_id, *, states=None, token=None, **fields):
        fields.setdefault("updated_at", time.time())
        if fields.get("cancel_requested") or fields.get("state", JobState.running) != JobState.running:
            # A change that brings a job to rest (cancelled, failed, back in the queue, a cancel
            # request) must go through on a full disk, as deletes do: else no job could be
            # cancelled there, nor a failed attempt leave "running". The claim and progress
            # writes need not: on a full disk no job should start.
            with self.lock:
                return self._freeing(lambda: self._update(job_id, states, token, fields))
        return self._update(job_id, states, token, fields)

    def _update(self, job_id, states, token, fields):
        with self.lock:
            self.db.execute("BEGIN IMMEDIATE")
            try:
                row = self.db.execute("SELECT data FROM jobs WHERE id=?", (job_id,)).fetchone()
                if row is None:
                    self._rollback()
                    return False
                job = Job.model_validate_json(row[0])
                if (states and job.state not in states) or (token and job.run_token != token):
                    self._rollback()
                    return False
                job = job.model_validate({**job.model_dump(), **fields, "version": job.version + 1})
                self.db.execute(
                    "UPDATE jobs SET state=?, data=? WHERE id=?",
                    (job.state.value, job.model_dump_json(), job_id),
                )
                self.db.execute("COMMIT")
                return True
            except BaseException:
                self._rollback()  # never hides the error (a failed COMMIT may have rolled back already)
                raise

    def _rollback(self) -> None:
        if self.db.in_transaction:
            try:
                self.db.execute("ROLLBACK")
            except sqlite3.Error:
                pass

    def _ensure_reserve(self) -> None:
        """Grow the reserve file back to its size as far as the disk allows (what does not fit
        now is taken back after a later write that frees space)."""
        if not self.reserve_bytes:
            return
        try:
            have = self.reserve.stat().st_size if self.reserve.exists() else 0
            if have >= self.reserve_bytes:
                return
            fd = os.open(self.reserve, os.O_WRONLY | os.O_CREAT, 0o600)
            try:
                while have < self.reserve_bytes:
                    have += os.pwrite(fd, bytes(min(1 << 20, self.reserve_bytes - have)), have)
                os.fsync(fd)
            except OSError:
                os.ftruncate(fd, have)  # what was written stays reserved
            finally:
                os.close(fd)
        except OSError:
            pass

    def _freeing(self, fn):
        """Run a write that must work on a full disk (a delete, a job brought to rest): on a
        full disk, give up a slice of the reserve and run it again, as long as the reserve
        lasts; then grow the reserve back as far as the disk allows. A slice at a time, so the
        room freed for this write is small and taken back at once: other writers on the disk
        (uploads, jobs) cannot use up the whole reserve in between."""
        try:
            while True:
                try:
                    return fn()
                except sqlite3.OperationalError as exc:
                    if not _disk_full(exc) or not self._give_up_slice():
                        raise
                    self._rollback()
        finally:
            self._ensure_reserve()

    def _give_up_slice(self) -> bool:
        try:
            size = self.reserve.stat().st_size
        except OSError:
            return False
        if size <= RESERVE_SLICE:
            self.reserve.unlink(missing_ok=True)
        else:
            os.truncate(self.reserve, size - RESERVE_SLICE)
        return size > 0

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
            rows = self.db.execute("SELECT data FROM jobs WHERE state='running'").fetchall()
        return [Job.model_validate_json(r[0]) for r in rows]

    def queued_ids(self):
        with self.lock:
            rows = self.db.execute("SELECT id FROM jobs WHERE state='queued' ORDER BY created_at").fetchall()
        return [r[0] for r in rows]

    def counts(self):
        with self.lock:
            rows = dict(self.db.execute("SELECT state, COUNT(*) FROM jobs GROUP BY state").fetchall())
        return {s.value: int(rows.get(s.value, 0)) for s in JobState}

    def claim_idempotency(self, owner, key, body_hash, job_id):
        k = f"{owner}:{key}"
        now = time.time()
        with self.lock:
            # as in Redis: a claim whose job was never created lapses after IDEM_PENDING_S,
            # one whose job exists after IDEM_TTL_S
            self.db.execute(
                "DELETE FROM idem WHERE k=? AND (at < ? OR (at < ? AND job_id NOT IN (SELECT id FROM jobs)))",
                (k, now - IDEM_TTL_S, now - IDEM_PENDING_S),
            )
            cur = self.db.execute(
                "INSERT OR IGNORE INTO idem VALUES (?,?,?,?)",
                (k, job_id, body_hash, time.time()),
            )
            if cur.rowcount == 1:
                return None
            row = self.db.execute("SELECT job_id, hash FROM idem WHERE k=?", (k,)).fetchone()
        return row[0], row[1]

    def release_idempotency(self, owner, key):
        with self.lock:
            self._freeing(lambda: self.db.execute("DELETE FROM idem WHERE k=?", (f"{owner}:{key}",)))

    def delete(self, job_id):
        with self.lock:
            row = self.db.execute("SELECT data FROM jobs WHERE id=?", (job_id,)).fetchone()
            if row is None:
                return False
            job = Job.model_validate_json(row[0])

            def delete():
                self.db.execute("BEGIN IMMEDIATE")
                try:
                    self.db.execute("DELETE FROM jobs WHERE id=?", (job_id,))
                    if job.idempotency_key:
                        k = f"{job.owner}:{job.idempotency_key}"
                        self.db.execute("DELETE FROM idem WHERE k=? AND job_id=?", (k, job_id))
                    self.db.execute("COMMIT")
                except BaseException:
                    self._rollback()
                    raise

            self._freeing(delete)
        return True

    def jobs(self):
        with self.lock:
            rows = self.db.execute("SELECT data FROM jobs").fetchall()
        return (Job.model_validate_json(r[0]) for r in rows)

    def asset_ids(self):
        with self.lock:
            return [r[0] for r in self.db.execute("SELECT id FROM assets").fetchall()]

    def add_blob_ref(self, key, asset_id):
        with self.lock:
            self.db.execute("INSERT OR IGNORE INTO blobrefs VALUES (?,?)", (key, asset_id))
            return self.db.execute("SELECT COUNT(*) FROM blobrefs WHERE k=?", (key,)).fetchone()[0]

    def remove_blob_ref(self, key, asset_id):
        with self.lock:
            self._freeing(lambda: self.db.execute("DELETE FROM blobrefs WHERE k=? AND asset_id=?", (key, asset_id)))
            return self.db.execute("SELECT COUNT(*) FROM blobrefs WHERE k=?", (key,)).fetchone()[0]

    def blob_lock(self, key):
        return self._blob_lock  # one process owns the file: a process-wide lock suffices

    def blob_ref_ids(self, key):
        with self.lock:
            return [r[0] for r in self.db.execute("SELECT asset_id FROM blobrefs WHERE k=?", (key,)).fetchall()]

    def delete_asset(self, asset_id):
        with self.lock:
            self._freeing(lambda: self.db.execute("DELETE FROM assets WHERE id=?", (asset_id,)))

    def put_asset(self, asset):
        with self.lock:
            self.db.execute(
                "INSERT OR REPLACE INTO assets VALUES (?,?)",
                (asset.id, asset.model_dump_json()),
            )

    def get_asset(self, asset_id):
        with self.lock:
            row = self.db.execute("SELECT data FROM assets WHERE id=?", (asset_id,)).fetchone()
        return Asset.model_validate_json(row[0]) if row else None

    def list_assets(self, owner, limit, cursor):
        # An index on the record's own members (assets_owner): rows stored before it are listed too.
        q = "SELECT data FROM assets WHERE json_extract(data, '$.owner')=?"
        args: list = [owner]
        if cursor is not None:
            q += " AND (json_extract(data, '$.created_at') < ? OR (json_extract(data, '$.created_at') = ? AND id < ?))"
            args += [cursor[0], cursor[0], cursor[1]]
        q += " ORDER BY json_extract(data, '$.created_at') DESC, id DESC LIMIT ?"
        args.append(limit)
        with self.lock:
            rows = self.db.execute(q, args).fetchall()
        return [Asset.model_validate_json(r[0]) for r in rows]

    def active_jobs(self, owner):
        with self.lock:
            q = "SELECT COUNT(*) FROM jobs WHERE owner=? AND state IN ('queued', 'running')"
            return int(self.db.execute(q, (owner,)).fetchone()[0])

    def set_usage(self, owner, item, nbytes):
        with self.lock:
            self.db.execute("INSERT OR REPLACE INTO usage VALUES (?,?,?)", (owner, item, int(nbytes)))
            return self.usage(owner)

    def drop_usage(self, owner, item):
        with self.lock:  # frees space: must work on a full disk, as deletes do
            self._freeing(lambda: self.db.execute("DELETE FROM usage WHERE owner=? AND item=?", (owner, item)))
            return self.usage(owner)

    def usage(self, owner):
        with self.lock:
            return int(
                self.db.execute("SELECT COALESCE(SUM(bytes), 0) FROM usage WHERE owner=?", (owner,)).fetchone()[0]
            )

    def record_stage(self, stage, seconds):
        with self.lock:
            self.db.execute(
                "INSERT INTO stages VALUES (?,1,?) ON CONFLICT(stage) DO UPDATE SET n=n+1, secs=secs+excluded.secs",
                (stage, seconds),
            )

    def stage_stats(self):
        with self.lock:
            return {s: (n, secs) for s, n, secs in self.db.execute("SELECT stage, n, secs FROM stages")}

    def ping(self):
        try:
            with self.lock:
                self.db.execute("SELECT 1")
            return True
        except sqlite3.Error:
            return False
