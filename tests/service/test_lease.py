"""The lease (hil.service.LeaseBook): only its holder's items run; it lapses without renewal, can be broken with a
reason, and outlives a restart of the service until it would have lapsed (docs/service.md, "The lease")."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.service import LeaseBook, LeaseError, Store


class Clock:
    def __init__(self) -> None:
        self.t = 1_000_000.0

    def __call__(self) -> float:
        return self.t


def test_only_the_holder_s_items_run_and_the_lease_lapses_without_renewal(tmp_path: Path) -> None:
    store, _ = Store.open(tmp_path)
    clock = Clock()
    book = LeaseBook(store, clock)
    assert book.current() is None and book.runs("ana") and book.runs("ben")
    book.take("ana", 30)
    assert book.runs("ana") and not book.runs("ben")
    with pytest.raises(LeaseError, match=r"^the bench is leased to ana for another 30 s; wait, or break"):
        book.take("ben", 30)
    clock.t += 25
    assert book.take("ana", 30).expires_s == clock.t + 30  # renewed
    clock.t += 29.9
    assert not book.runs("ben")
    clock.t += 0.1  # the client went away: no renewal within the TTL
    assert book.current() is None and book.runs("ben")
    events = store.lease_events()
    assert [e["event"] for e in events] == ["lapsed", "taken"] and events[0]["reason"] == "not renewed within 30 s"
    with pytest.raises(LeaseError, match=r"^ttl_s=1: need 5..86400 s$"):
        book.take("ana", 1)
    with pytest.raises(LeaseError, match="ben holds no lease"):
        book.release("ben")


def test_a_lease_broken_by_another_operator_says_why_and_a_restart_keeps_a_live_one(tmp_path: Path) -> None:
    store, _ = Store.open(tmp_path)
    clock = Clock()
    LeaseBook(store, clock).take("ana", 600)
    store.close()
    store, _ = Store.open(tmp_path)  # the service restarted: the lease is still ana's
    book = LeaseBook(store, clock)
    assert not book.runs("ben") and book.current() is not None
    with pytest.raises(LeaseError, match="reason: say why"):
        book.break_("ben", "  ")
    assert book.break_("ben", "ana left for the day;\nthe swing table is needed").holder == "ana"
    assert book.runs("ben")
    broken = store.lease_events()[0]
    assert (broken["event"], broken["holder"], broken["by"], broken["reason"]) == (
        "broken", "ana", "ben", "ana left for the day; the swing table is needed")
    store.close()
    store, _ = Store.open(tmp_path)
    assert LeaseBook(store, clock).current() is None
    book = LeaseBook(store, clock)
    book.take("ben", 60)
    book.release("ben")
    assert [e["event"] for e in store.lease_events()] == ["released", "taken", "broken", "taken"]
