"""The edge pool of many jobs (service.worker.edges) against a real redis-server: a helper that
dies mid-edge leaves a claim that lapses, and the parent runs that edge itself; a helper that
fails gives its edge back at once."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import redis

from gsa.align.pipeline import AlignOptions
from gsa.sim3 import Sim3
from gsa.synth import make_object
from service.worker.edges import LocalEdgePool, RedisEdgePool, edge_from_payload, work_through
from service.worker.leases import worker_name

OPTIONS = AlignOptions(stages=("coarse",), coarse_iterations=20, seed=0)


@pytest.fixture
def models():
    m = make_object("car", seed=0, n_gaussians=800)
    return [m, m.transformed(Sim3(1.5, np.eye(3), np.array([0.2, 0.0, -0.1])))]


@pytest.fixture
def conn(redis_url):
    r = redis.Redis.from_url(redis_url + "/5")  # private test server
    yield r
    r.flushdb()


def test_a_lapsed_claim_is_run_by_the_parent(conn, models):
    pool = RedisEdgePool(conn, "job_edges", "token")
    pool.create([(0, 1), (1, 0)], ttl_s=600)
    assert pool.claim("dead-helper") == 0  # a helper claims edge 0 ...
    assert pool.lapsed() == []  # ... and while its claim runs, nobody else takes the edge
    conn.hset(pool.k_claims, "0", json.dumps({"worker": "dead-helper", "until": time.time() - 1}))
    assert pool.lapsed() == [0]  # ... then dies without renewing it
    payloads = work_through(pool, models, OPTIONS, check=lambda: None, poll_s=0.01)
    assert [p["worker"] for p in payloads] == [worker_name()] * 2
    forward, backward = (edge_from_payload(i, j, p) for (i, j), p in zip(pool.pairs, payloads))
    assert forward.transform.scale == pytest.approx(1.5, rel=0.02)
    assert backward.transform.scale == pytest.approx(1 / 1.5, rel=0.02)
    assert conn.hlen(pool.k_claims) == 0  # finished edges hold no claim
    pool.delete()
    assert RedisEdgePool(conn, "job_edges", "token").pairs is None  # a late helper finds no pool


def test_a_failed_edge_goes_back_to_the_pool(conn):
    pool = RedisEdgePool(conn, "job_edges", "token2")
    pool.create([(0, 1), (0, 2), (1, 2)], ttl_s=600)
    assert pool.claim("helper") == 0
    pool.release(0)
    assert [pool.claim("parent") for _ in range(4)] == [0, 1, 2, None]


def test_the_local_pool_runs_every_edge_in_order(models):
    pool = LocalEdgePool([(0, 1), (1, 0)])
    seen = []
    payloads = work_through(pool, models, OPTIONS, check=lambda: None, on_edge=lambda k, n, s, f: seen.append(k))
    assert len(payloads) == 2 and sorted(set(seen)) == [0, 1]


def test_the_parent_stops_when_checked_out(conn, models):
    class Cancelled(Exception):
        pass

    def check():
        raise Cancelled

    pool = RedisEdgePool(conn, "job_edges", "token3")
    pool.create([(0, 1)], ttl_s=600)
    with pytest.raises(Cancelled):
        work_through(pool, models, OPTIONS, check=check)
    assert pool.claim("other") == 0  # nothing was claimed before the check stopped it


def test_a_lost_pool_is_put_back_with_the_results_it_still_has(conn, models):
    """Redis lost the pool's keys (a restart without persistence): the parent puts it back and
    finishes; a result that survived is kept, not run again."""
    pool = RedisEdgePool(conn, "job_edges", "token4")
    pool.create([(0, 1), (1, 0)], ttl_s=600)
    kept = {"transform": np.eye(4).tolist(), "confidence": 1.0, "doubtful": False, "ambiguous": False}
    kept |= {"alternatives": [], "seconds": 0.0, "worker": "earlier"}
    assert pool.claim("helper") == 0
    conn.delete(pool.k_pairs, pool.k_pending, pool.k_claims)  # the pool's keys go; edge 0's result ...
    conn.hset(pool.k_results, "0", json.dumps(kept))  # ... survived in this case
    payloads = work_through(pool, models, OPTIONS, check=lambda: None, poll_s=0.01)
    assert payloads[0]["worker"] == "earlier" and payloads[1]["worker"] == worker_name()
    assert pool.pairs == [(0, 1), (1, 0)] and conn.exists(pool.k_pairs)


def test_an_edge_payload_keeps_the_scores_of_its_poses():
    # Through a worker's pool (JSON in Redis) the global step still sees how plausible the
    # tie-break found each pose (gsa.align.many.pose_weights).
    from gsa.align.many import Edge
    from service.worker.edges import edge_payload

    turned = Sim3(1.0, np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    edge = Edge(0, 1, Sim3.identity(), confidence=0.1, doubtful=True, alternatives=[turned], scores=[0.2, None])
    edge.agreements, edge.agreement_needed = [0.12, 0.01], 0.05
    back = edge_from_payload(0, 1, json.loads(json.dumps(edge_payload(edge, "w"))))
    assert back.scores == [0.2, None] and np.allclose(back.alternatives[0].rotation, turned.rotation)
    assert back.agreements == [0.12, 0.01] and back.agreement_needed == 0.05  # and the local shapes' shares
