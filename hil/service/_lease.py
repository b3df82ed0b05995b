"""The lease: an operator takes the bench for a while, and only their items run (docs/service.md, "The lease").

A lease has a time-to-live that its holder's client renews; it lapses by itself when the client goes away (no
renewal within the TTL), the way labgrid's places release when a CI job is cancelled. Another operator may break it,
with a reason. Every change goes into the store's lease history, and the lease itself (holder and wall-clock expiry)
into its settings, so a restarted service keeps a lease until it would have lapsed. A lease lapses when its time is up
even while the store takes no writes (its disk full): the lapse is recorded once it does.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from hil.service._store import Store, StoreError

MIN_TTL_S = 5.0
MAX_TTL_S = 24 * 3600.0


class LeaseError(StoreError):
    """A lease request that cannot be granted (held by another operator, not held, a bad TTL): one line."""


@dataclass(frozen=True)
class Lease:
    holder: str
    ttl_s: float
    expires_s: float  # wall clock (time.time()), so that it survives a restart of the service

    def public(self, now_s: float) -> dict[str, Any]:
        return {**asdict(self), "remaining_s": round(max(0.0, self.expires_s - now_s), 3)}


class LeaseBook:
    """Who holds the bench now. ``clock``: wall-clock seconds (``time.time``; a test gives its own)."""

    def __init__(self, store: Store, clock: Callable[[], float] = time.time) -> None:
        self.store = store
        self.clock = clock
        saved = store.setting("lease")
        self._lease = Lease(**saved) if saved else None
        self._lapsed: Lease | None = None  # a lapse not recorded yet (the store took no writes)

    def current(self) -> Lease | None:
        """The lease in force, or None; a lease past its expiry lapses here, and is recorded so (StoreUnavailable
        if the store cannot record it now: the lease has lapsed all the same, and is recorded at the next call)."""
        lease = self._lease
        if lease is not None and self.clock() >= lease.expires_s:
            self._lease, self._lapsed = None, lease
        self._record_lapse()
        return self._lease

    def _record_lapse(self) -> None:
        lapsed = self._lapsed
        if lapsed is None:
            return
        if self._lease is None:
            self.store.set_setting("lease", None)
        self.store.lease_event("lapsed", lapsed.holder, lapsed.holder, f"not renewed within {lapsed.ttl_s:g} s")
        self._lapsed = None

    def runs(self, user: str) -> bool:
        """May an item of ``user`` run now? Anyone's when no lease is held, else only the holder's."""
        lease = self.current()
        return lease is None or lease.holder == user

    def take(self, user: str, ttl_s: float) -> Lease:
        """Take the bench for ``ttl_s`` (renewed by taking it again); LeaseError if another operator holds it."""
        if not (isinstance(ttl_s, int | float) and math.isfinite(ttl_s) and MIN_TTL_S <= ttl_s <= MAX_TTL_S):
            raise LeaseError(f"ttl_s={ttl_s!r}: need {MIN_TTL_S:g}..{MAX_TTL_S:g} s")
        lease = self.current()
        if lease is not None and lease.holder != user:
            raise LeaseError(f"the bench is leased to {lease.holder} for another "
                             f"{lease.expires_s - self.clock():.0f} s; wait, or break the lease with a reason")
        new = Lease(user, float(ttl_s), self.clock() + ttl_s)
        self._set(new)
        if lease is None:
            self.store.lease_event("taken", user, user, f"ttl {ttl_s:g} s")
        return new

    def release(self, user: str) -> None:
        lease = self.current()
        if lease is None or lease.holder != user:
            raise LeaseError(f"{user} holds no lease" + (f" (it is {lease.holder}'s)" if lease else ""))
        self._set(None)
        self.store.lease_event("released", user, user)

    def break_(self, by: str, reason: str) -> Lease:
        """End another operator's lease; the reason goes into the lease history."""
        if not reason.strip():
            raise LeaseError("reason: say why the lease is broken (it goes into the history)")
        lease = self.current()
        if lease is None:
            raise LeaseError("no lease is held")
        self._set(None)
        self.store.lease_event("broken", lease.holder, by, reason)
        return lease

    def _set(self, lease: Lease | None) -> None:
        """Record ``lease`` in the store, then hold it (StoreUnavailable: neither)."""
        self.store.set_setting("lease", None if lease is None else asdict(lease))
        self._lease = lease
