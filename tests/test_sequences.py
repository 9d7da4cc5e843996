"""`jaxfish._sequences`: what a process keeps of the sequences it builds, per owner, for at most
`sequence_slots` owners."""

from __future__ import annotations

import threading

import pytest

from jaxfish._sequences import KeptByOwner, acting_for, sequence_owner, sequence_slots, set_sequence_slots
from jaxfish.pipeline import set_sequence_slots as public_setter


@pytest.fixture
def slots():
    before = sequence_slots()
    yield set_sequence_slots
    set_sequence_slots(before)


def test_an_owner_replaces_its_own_entry_and_the_least_recent_owner_goes_first(slots):
    store = KeptByOwner()
    slots(2)
    store.put("FV", 0, owner="a")
    store.put("FV", 10, owner="b")
    store.put("FV", 1, owner="a")  # a's next frame replaces a's entry, not b's
    assert store.values("FV", owner="a") == [1, 10] and store.values("FV", owner="b") == [10, 1]
    store.put("FV", 20, owner="c")  # a third owner: b was the least recently active
    assert store.values("FV", owner="c") == [20, 1]
    slots(1)  # fewer slots drop the least recent owners at once
    assert store.values("FV", owner="a") == [20]
    store.pop("FV", owner="c")
    assert store.values("FV") == []


def test_one_slot_keeps_the_last_entry_whichever_thread_put_it(slots):
    """A serial build's behaviour: a lookup from any thread finds the last entry."""
    store = KeptByOwner()
    slots(1)
    store.put("k", "main")
    seen = []
    t = threading.Thread(target=lambda: (seen.extend(store.values("k")), store.put("k", "thread")))
    t.start()
    t.join()
    assert seen == ["main"] and store.values("k") == ["thread"]


def test_a_helper_thread_keeps_what_it_keeps_for_the_owner_it_acts_for(slots):
    store = KeptByOwner()
    slots(2)
    owner = sequence_owner()
    assert owner == threading.get_ident()

    def helper():
        with acting_for(owner):
            assert sequence_owner() == owner
            store.put("k", 1)
        assert sequence_owner() == threading.get_ident()
        store.put("k", 2)

    t = threading.Thread(target=helper)
    t.start()
    t.join()
    assert store.values("k") == [1, 2]


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_set_sequence_slots_refuses_anything_but_a_positive_integer(bad):
    with pytest.raises(ValueError, match="sequence slots must be an integer >= 1"):
        set_sequence_slots(bad)


def test_the_setter_is_public_and_returns_the_previous_value(slots):
    before = sequence_slots()
    assert public_setter(3) == before and sequence_slots() == 3
