"""Blocks in backoff sleep apart (:mod:`streamer.loadqueue`): the queue pops exactly what it
popped when they stayed in the urgency heaps, and a pop during an outage no longer touches
every queued block. The reference is the pop before the change (4606c39, kept by the benchmark),
run on the same operations; its cost is the positive control of the count.

Two differences are by design, both for a block that sleeps while another level of it is
read: a success wakes it at once into the heap of blocks that have not failed (the old queue
left it where a pop last put it, so a block no longer failed still waited among the failed
ones), and a failure is seen when it wakes (its turn by its latest failure; the old queue used
the failure it knew when a pop last met it). The random sequences leave sleeping blocks' reads
out; the success has its own test."""

from __future__ import annotations

import random
import sys
from pathlib import Path

import pytest

from streamer.loadqueue import LoadQueue

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from bench.outage_queue import old_pop  # noqa: E402


class OldQueue(LoadQueue):
    """The queue before sleeping: blocks in backoff popped and pushed back by every pop (the
    pop of 4606c39, kept in ``bench/outage_queue.py`` as that benchmark's "before")."""

    pop = old_pop

    def rebuild(self, items, now=None):
        super().rebuild(items)  # (nothing sleeps)


def _take(b):
    return None if (b[0] * 7 + b[1]) % 11 == 0 else ("job", b)  # some blocks are refused


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("heal", [True, False])
def test_the_queue_pops_what_it_popped_before(seed, heal):
    rng = random.Random(seed)
    kw = {"retries": rng.choice([1, 2, 3]), "backoff_s": 0.05, "max_backoff_s": 0.4, "heal": heal}
    new, old = LoadQueue(**kw), OldQueue(**kw)
    blocks = [(r, c) for r in range(6) for c in range(6)]
    now, popped = 0.0, 0
    for _ in range(600):
        op = rng.random()
        b = rng.choice(blocks)
        if op < 0.35:
            key = (rng.randint(0, 1), rng.randint(0, 1), rng.random())
            new.push(b, key)
            old.push(b, key)
        elif op < 0.6:
            probe = rng.random() < 0.7
            got = new.pop(now, _take, probe)
            assert got == old.pop(now, _take, probe)
            popped += got is not None
        elif op < 0.86 and b in new._asleep:
            continue  # (the difference by design: module doc)
        elif op < 0.78:
            new.failed_read(b, now)
            old.failed_read(b, now)
        elif op < 0.86:
            new.succeeded(b)
            old.succeeded(b)
        elif op < 0.9:
            items = [((rng.randint(0, 1), 0, rng.random()), x) for x in rng.sample(blocks, 12)]
            new.rebuild(items, now)
            old.rebuild(items, now)
            assert new.cancelled == old.cancelled
        else:
            now += rng.choice([0.01, 0.1, 0.5])
        assert len(new) == len(old) and new.blocks() == old.blocks()
        assert all(new.queued_key(x) == old.queued_key(x) for x in blocks)
    assert popped > 20  # the sequences popped enough to compare


def _outage(cls, n=1000):
    """``n`` queued blocks that all failed their reads just now (a server gone)."""
    q = cls(retries=3, backoff_s=0.1, max_backoff_s=1.0)
    items = []
    for i in range(n):
        b = (i // 100, i % 100)
        for _ in range(3):
            q.failed_read(b, 100.0)
        items.append(((0, 0, float(i)), b))
    q.rebuild(items, 100.0)
    return q


def _checks_per_pop(q, monkeypatch) -> int:
    calls = 0
    backing_off = type(q).backing_off

    def counted(self, b, now):
        nonlocal calls
        calls += 1
        return backing_off(self, b, now)

    monkeypatch.setattr(type(q), "backing_off", counted)
    for _ in range(5):
        assert q.pop(100.2, _take) is None  # every block waits for its retry (at 100.4)
    return calls // 5


def test_a_pop_during_an_outage_touches_no_sleeping_block(monkeypatch):
    q = _outage(LoadQueue)
    assert _checks_per_pop(q, monkeypatch) == 0
    assert len(q) == 1000
    got = q.pop(101.5, _take)  # their retry time has come: the most urgent goes
    assert got == ((0, 1), ("job", (0, 1)))  # ((0, 0) is refused by take)


def test_positive_control_the_old_pop_touches_every_queued_block(monkeypatch):
    assert _checks_per_pop(_outage(OldQueue), monkeypatch) == 1000


@pytest.mark.parametrize("cls", [LoadQueue, OldQueue])
def test_a_success_wakes_a_sleeping_block_as_one_not_failed(cls):
    q = cls(retries=1, backoff_s=1.0, max_backoff_s=1.0)
    b, other = (2, 2), (3, 3)
    q.failed_read(b, 0.0)  # failed (one retry): it waits among the failed blocks
    q.push(b, (0, 0, 0.0))
    assert q.pop(0.1, _take) is None  # in backoff: asleep
    q.succeeded(b)  # another level of it was read: not failed, no backoff any more
    q.push(other, (1, 1, 0.5))  # less urgent, never failed
    first = q.pop(0.2, _take, probe=False)  # (failed blocks only when nothing else can go)
    if cls is LoadQueue:
        assert first == (b, ("job", b))
    else:  # the old queue: b still waits among the failed, behind a less urgent block
        assert first == (other, ("job", other))
