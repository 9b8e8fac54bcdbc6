"""GSA_STORAGE_QUOTA_BYTES: local storage that fails like a full disk past its quota."""

from __future__ import annotations

import errno
import io

import httpx
import pytest

from service.problems import infrastructure_problem
from service.storage import LocalStorage
from tests.service.conftest import ALICE, assert_problem, service_env, start_api


def test_a_write_past_the_quota_fails_as_a_full_disk_and_leaves_nothing(tmp_path):
    st = LocalStorage(tmp_path / "blobs", quota_bytes=10_000)
    assert st.put("uploads/a/one.bin", io.BytesIO(b"x" * 6000)) == 6000
    assert st.free_bytes() == 4000
    with pytest.raises(OSError) as err:
        st.put("uploads/b/two.bin", io.BytesIO(b"y" * 6000))
    assert err.value.errno == errno.ENOSPC
    assert infrastructure_problem(err.value).status == 507
    assert not st.exists("uploads/b/two.bin")
    assert [p.name for p in (tmp_path / "blobs").rglob("*") if p.is_file()] == ["one.bin"]
    st.delete("uploads/a/one.bin")
    assert st.used_bytes(max_age_s=0) == 0
    st.put("uploads/b/two.bin", io.BytesIO(b"y" * 6000))  # room again


def test_usage_counts_what_other_processes_stored(tmp_path):
    mine = LocalStorage(tmp_path / "blobs", quota_bytes=10_000)
    other = LocalStorage(tmp_path / "blobs", quota_bytes=10_000)  # another worker on the folder
    other.put("jobs/j/t/result.json", io.BytesIO(b"z" * 9000))
    assert mine.used_bytes(max_age_s=0) == 9000
    with pytest.raises(OSError):
        mine.put("uploads/a/x.bin", io.BytesIO(b"x" * 2000))


def test_no_quota_by_default(tmp_path):
    st = LocalStorage(tmp_path / "blobs")
    assert st.free_bytes() is None
    st.put("uploads/a/one.bin", io.BytesIO(b"x" * 100_000))


@pytest.mark.slow
def test_upload_past_the_quota_is_507_and_readyz_reports_it(tmp_path, pair):
    size = pair["source"].stat().st_size
    # The global quota alone: a tenant's own (by default half of it, service.jobs.quotas) is tested in test_tenant_limits.
    env = service_env(
        tmp_path, GSA_STORAGE_QUOTA_BYTES=int(size * 1.05), GSA_MIN_FREE_BYTES=size, GSA_TENANT_STORAGE_QUOTA_BYTES=0
    )
    api, url, _ = start_api(tmp_path, env, name="api-quota")
    try:
        with httpx.Client(base_url=url, headers=ALICE, timeout=60) as c:
            assert c.get("/readyz").status_code == 200
            with open(pair["source"], "rb") as fh:
                assert c.post("/v1/assets", files={"file": ("a.ply", fh)}).status_code == 201
            with open(pair["target"], "rb") as fh:
                r = c.post("/v1/assets", files={"file": ("b.ply", fh)})
            assert_problem(r, 507, "insufficient-storage")
            ready = c.get("/readyz")  # under a tenth of the quota left
            assert ready.status_code == 503 and ready.json()["checks"]["disk_space"] is False, ready.text
            assert c.get("/healthz").status_code == 200  # the keep-alive connection still serves
    finally:
        api.stop()
