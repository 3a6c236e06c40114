"""What the collector knows about its agents (collector/agents.py), on its own."""

from __future__ import annotations

from bgt_core.messages import AgentStatus
from collector.agents import AgentBook


def test_liveliness_and_status_fetches() -> None:
    book = AgentBook()
    book.set_alive("pi-1", True)
    book.set_alive("pi-2", True)
    book.set_alive("pi-2", False)
    assert book.alive_map() == {"pi-1": True, "pi-2": False}
    assert book.alive_agents() == {"pi-1"}
    # a status is fetched once: the first claim wins until it is fetched or known
    assert book.claim_fetch("pi-1")
    assert not book.claim_fetch("pi-1")
    book.fetched("pi-1")
    assert book.claim_fetch("pi-1")
    book.set_info("pi-1", AgentStatus("pi-1"))
    book.fetched("pi-1")
    assert not book.claim_fetch("pi-1")  # known now: no need to ask again
    assert list(book.infos()) == ["pi-1"]


def test_last_acknowledgement_and_spool_reach_the_status() -> None:
    from bgt_core.control_messages import AgentLive

    book = AgentBook()
    book.acked("pi-1", now=100.0)
    book.acked("pi-1", now=103.5)
    assert book.last_acks() == {"pi-1": 103.5}
    live = AgentLive(True, {}, spool_records=12, spool_bytes=4096, last_ack_age_s=0.4)
    back = AgentLive.from_dict(live.to_dict())
    assert back == live
    assert AgentLive.from_dict({"alive": True}).spool_records is None  # older collectors
