"""Signed browser links (service.api.view_links): what opens a page and what does not."""

from __future__ import annotations

import pytest

from service.api.view_links import LinkError, sign, verify


def test_a_link_opens_its_page_for_its_owner_until_it_expires():
    token, expires = sign("s3cret", "job:a", "alice", 60, now=1000.0)
    assert expires == 1060 and "alice" not in token and "s3cret" not in token
    grant = verify("s3cret", "job:a", token, now=1059.0)
    assert (grant.owner, grant.expires_at) == ("alice", 1060)
    with pytest.raises(LinkError) as e:
        verify("s3cret", "job:a", token, now=1061.0)
    assert e.value.expired


@pytest.mark.parametrize(
    "change",
    [
        lambda t: t.replace(".106", ".999", 1),  # a later expiry
        lambda t: "v1." + "Ym9i" + t[t.index(".", 3) :],  # another owner ("bob")
        lambda t: t[:-3] + ("AAA" if t[-3:] != "AAA" else "BBB"),  # the signature
        lambda t: t.replace("v1.", "v2.", 1),
        lambda t: t + ".x",
        lambda t: "",
        lambda t: "v1.!!.1.x",
        lambda t: "v1." + "A" * 5000,
    ],
)
def test_an_altered_or_malformed_token_is_refused(change):
    token, _ = sign("s3cret", "job:a", "alice", 60, now=1000.0)
    with pytest.raises(LinkError) as e:
        verify("s3cret", "job:a", change(token), now=1001.0)
    assert not e.value.expired


def test_another_page_or_another_key_refuses_it():
    token, _ = sign("s3cret", "job:a", "alice", 60, now=1000.0)
    for scope, secret in (("job:b", "s3cret"), ("jobs", "s3cret"), ("job:a", "other")):
        with pytest.raises(LinkError):
            verify(secret, scope, token, now=1001.0)
    # Without a configured secret the process's own random key signs and verifies.
    t, _ = sign(None, "jobs", "alice", 60)
    assert verify(None, "jobs", t).owner == "alice"
    with pytest.raises(LinkError):
        verify("s3cret", "jobs", t)
