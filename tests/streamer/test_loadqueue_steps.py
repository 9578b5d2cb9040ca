"""``LoadQueue.rebuild_steps``: the planning thread rebuilds the load queue in steps, releasing
the session's lock between them (one rebuild of ~600 blocks held it for ~0.5 ms). Run to the
end it leaves the queue the one-hold rebuild before it left (kept here as the reference); until
its last step the queue is untouched; a block that recovers between the steps is not lost."""

from __future__ import annotations

import heapq
import random

import pytest

from streamer.loadqueue import LoadQueue

BLOCKS = [(r, c) for r in range(6) for c in range(6)]


class OneHold(LoadQueue):
    """The rebuild before the steps (0fda539), in one piece."""

    def rebuild(self, items, now=None):
        before = self.blocks()
        self._heap, self._failed = [], []
        self._drop_sleepers()
        best = {}
        for k, b in items:
            if self.retryable(b):
                if now is not None and self.backing_off(b, now):
                    self._sleep(k, b)
                elif self.is_failed(b):
                    self._failed.append(self._failed_entry(k, b))
                else:
                    self._heap.append((k, b))
                if b not in best or k < best[b]:
                    best[b] = k
        heapq.heapify(self._heap)
        heapq.heapify(self._failed)
        self._best = best
        self.cancelled += len(before - best.keys())


def _state(q: LoadQueue) -> tuple:
    """What the queue holds, and where: sleeping, failed or in the urgency heap (a block in
    backoff put on the urgency heap would pop the same, but cost every pop a check again)."""
    where = (sorted(q._asleep.items()), sorted(q._heap), sorted(q._failed))
    return (len(q), q.blocks(), [q.queued_key(b) for b in BLOCKS], q.cancelled, where)


def _take(b):
    return None if (b[0] * 5 + b[1]) % 7 == 0 else ("job", b)


def _pops(q: LoadQueue, now: float) -> list:
    return [q.pop(now, _take, probe=i % 2 == 0) for i in range(8)]


def _queues(seed: int) -> tuple[list[LoadQueue], float, random.Random]:
    """Two queues (steps, one hold) with the same random failures, backoffs and contents."""
    rng = random.Random(seed)
    kw = {"retries": rng.choice([1, 2, 3]), "backoff_s": 0.05, "max_backoff_s": 0.4}
    qs = [LoadQueue(**kw), OneHold(**kw)]
    now = 0.0
    for _ in range(60):
        b = rng.choice(BLOCKS)
        op = rng.random()
        for q in qs:
            if op < 0.4:
                q.push(b, (rng.randint(0, 1), 0, round(op, 3)))
            elif op < 0.75:
                q.failed_read(b, now)
            elif op < 0.85:
                q.succeeded(b)
        now += 0.01 if op > 0.9 else 0.0
    return qs, now, rng


@pytest.mark.parametrize("seed", range(30))
@pytest.mark.parametrize("chunk", [1, 4, 64])
def test_rebuild_in_steps_leaves_the_queue_of_the_one_hold_rebuild(seed, chunk):
    (steps, ref), now, rng = _queues(seed)
    items = [((rng.randint(0, 1), rng.randint(0, 1), rng.random()), b)
             for b in rng.sample(BLOCKS, 20)]  # fmt: skip
    items += [((0, 0, -1.0), b) for _, b in items[:3]]  # twice: the most urgent key counts
    before = _state(steps)
    gen = steps.rebuild_steps(list(items), now, chunk)
    for n, _ in enumerate(gen, 1):
        if n <= -(-len(items) // chunk):  # the sorting steps: nothing in place yet
            assert _state(steps) == before
    ref.rebuild(list(items), now)
    assert _state(steps) == _state(ref)
    for t in (now, now + 0.2):  # (at ``now`` the blocks in backoff sleep)
        assert _pops(steps, t) == _pops(ref, t)
        assert _state(steps) == _state(ref)


def test_the_comparison_sees_a_rebuild_that_drops_backoff():
    """The control: a rebuild that queues blocks in backoff with the others (no sleep) is
    told apart from the reference by the same observations."""

    class NoSleep(LoadQueue):
        def backing_off(self, b, now):
            return False

    differ = 0
    for seed in range(30):
        (_, ref), now, rng = _queues(seed)
        q = NoSleep(retries=ref.retries, backoff_s=0.05, max_backoff_s=0.4)
        q.failures, q.retry_at, q.failed_at = ref.failures, ref.retry_at, ref.failed_at
        items = [((0, 0, rng.random()), b) for b in rng.sample(BLOCKS, 20)]
        q.rebuild(list(items), now)
        ref.rebuild(list(items), now)
        differ += _pops(q, now) != _pops(ref, now)
    assert differ >= 5, differ


def test_a_block_that_recovers_between_the_steps_is_queued():
    q = LoadQueue(retries=2, backoff_s=1.0, max_backoff_s=4.0)
    b = (1, 1)
    q.failed_read(b, 10.0)  # in backoff until 11.0
    gen = q.rebuild_steps([((0, 0, 0.5), b)], 10.5, 64)
    next(gen)  # sorted: asleep
    q.succeeded(b)  # its other level's read worked meanwhile
    for _ in gen:
        pass
    assert q.queued_key(b) == (0, 0, 0.5) and len(q) == 1
    assert q.pop(10.5, _take) == (b, ("job", b))  # at once, not at its old retry time


class _Watched(list):
    """An old heap that counts the entries read from it."""

    def __init__(self, items, seen):
        super().__init__(items)
        self.seen = seen

    def __iter__(self):
        for x in list.__iter__(self):
            self.seen[0] += 1
            yield x

    def __getitem__(self, i):
        out = list.__getitem__(self, i)
        self.seen[0] += len(out) if isinstance(i, slice) else 1
        return out


def _watched_rebuild(q: LoadQueue, chunk: int) -> list[int]:
    """Rebuild a queue of 400 blocks with 100 of them, ``chunk`` per step; the entries of
    the old heap each step read."""
    blocks = [(r, c) for r in range(20) for c in range(20)]
    for i, b in enumerate(blocks):
        q.push(b, (1, 1, i))
    seen = [0]
    q._heap = _Watched(q._heap, seen)
    per_step = []
    for _ in q.rebuild_steps([((0, 0, i), b) for i, b in enumerate(blocks[::4])], 0.0, chunk):
        per_step.append(seen[0])
        seen[0] = 0
    per_step.append(seen[0])
    assert q.cancelled == 300 and len(q) == 100
    return per_step


def test_no_step_of_a_rebuild_walks_the_old_queue():
    """The cancelled loads are counted in steps after the swap, ``4 * chunk`` old entries
    each; the swap itself reads none (it walked the whole old queue: a step of O(queue))."""
    per_step = _watched_rebuild(LoadQueue(retries=2, backoff_s=0.1, max_backoff_s=1.0), 8)
    assert max(per_step) == 32 and sum(per_step) == 400, per_step


class _OneHoldSteps(OneHold):
    def rebuild_steps(self, items, now=None, chunk=64):
        self.rebuild(items, now)
        yield


def test_positive_control_the_one_hold_rebuild_walks_it():
    per_step = _watched_rebuild(_OneHoldSteps(retries=2, backoff_s=0.1, max_backoff_s=1.0), 8)
    assert max(per_step) == 400, per_step


def _sleeps_per_step(q: LoadQueue) -> list[int]:
    """Rebuild a queue with 300 blocks in backoff, 16 a step: the blocks put to sleep by
    ``_sleep`` in each step (the sort builds its own sleeping heap)."""
    blocks = [(r, c) for r in range(20) for c in range(15)]
    for b in blocks:
        q.failed_read(b, 10.0)  # in backoff until 11.0
    calls = [0]
    real = q._sleep

    def sleep(key, b):
        calls[0] += 1
        real(key, b)

    q._sleep = sleep
    per_step = []
    for _ in q.rebuild_steps([((0, 0, i), b) for i, b in enumerate(blocks)], 10.5, 16):
        per_step.append(calls[0])
        calls[0] = 0
    per_step.append(calls[0])
    assert len(q) == 300 and q.pop(10.5, _take) is None  # all asleep
    return per_step


def test_the_swap_does_not_put_every_sleeper_to_sleep_again():
    """During an outage most of the queue sleeps; the swap re-slept every sleeper in one
    step (a hold of hundreds of µs)."""
    assert sum(_sleeps_per_step(LoadQueue(retries=3, backoff_s=1.0, max_backoff_s=4.0))) == 0


def test_positive_control_the_one_hold_rebuild_sleeps_them_in_one_step():
    per_step = _sleeps_per_step(_OneHoldSteps(retries=3, backoff_s=1.0, max_backoff_s=4.0))
    assert max(per_step) == 300, per_step


def test_a_block_that_recovers_and_fails_again_between_the_steps_sleeps():
    """As the one-hold rebuild decided at its swap: a block back in backoff sleeps."""
    q = LoadQueue(retries=2, backoff_s=1.0, max_backoff_s=4.0)
    b = (1, 1)
    q.failed_read(b, 10.0)
    gen = q.rebuild_steps([((0, 0, 0.5), b)], 10.5, 64)
    next(gen)
    q.succeeded(b)
    q.failed_read(b, 10.6)  # in backoff again until 11.6
    for _ in gen:
        pass
    assert q.queued_key(b) == (0, 0, 0.5) and len(q) == 1
    assert q.pop(11.0, _take) is None  # asleep
    assert q.pop(11.7, _take) == (b, ("job", b))


@pytest.mark.parametrize("large", [False, True])
def test_a_block_that_recovers_just_before_the_swap_is_queued(large):
    """A recovery in the last pause before the swap (after a small queue's heapify step, or
    after a large queue's last sort step) wakes the block at the swap, as the one-hold
    rebuild's check of every sleeper did."""
    q = LoadQueue(retries=2, backoff_s=1.0, max_backoff_s=4.0)
    b = (1, 1)
    q.failed_read(b, 10.0)  # in backoff until 11.0
    others = [((1, 1, float(i)), (5, i)) for i in range(300 if large else 3)]
    items = [((0, 0, 0.5), b), *others]
    gen = q.rebuild_steps(items, 10.5, 64)
    sorting = -(-len(items) // 64) + (0 if large else 1)  # the steps before the swap
    for _ in range(sorting):
        next(gen)
    assert q.queued_key(b) is None  # not swapped in yet
    q.succeeded(b)
    for _ in gen:
        pass
    assert q.queued_key(b) == (0, 0, 0.5)
    assert q.pop(10.5, _take) == (b, ("job", b))  # at once, not at its old retry time
