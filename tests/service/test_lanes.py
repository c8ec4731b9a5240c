"""Lanes and deadlines (service.lanes): bounded capacity, shedding, deadlines, hand-off.
Threads are held on events, so every count is exact and no test depends on timing."""

import os
import threading

import anyio
import pytest

from service import lanes
from service.lanes import DeadlineExceeded, Heavy, Lane, Lanes, Overloaded, Threaded, Waiting


def test_a_full_lane_sheds_at_once_and_frees_its_slots_after():
    lane = Lane("light", threads=2, queue=1)
    release, started = threading.Event(), threading.Semaphore(0)

    def held():
        started.release()
        release.wait(10)
        return "done"

    async def main():
        results, refused = [], []

        async def call():
            try:
                results.append(await lane.run(held))
            except Overloaded as exc:
                refused.append(exc)

        async with anyio.create_task_group() as tg:
            for _ in range(3):  # two at work, one waiting
                tg.start_soon(call)
            for _ in range(2):
                await anyio.to_thread.run_sync(started.acquire)
            await anyio.sleep(0.05)
            assert (lane.stats.admitted, lane.stats.busy) == (3, 2)
            await call()  # the fourth: refused without waiting
            assert len(refused) == 1 and refused[0].retry_after_s == 1 and lane.stats.shed == 1
            release.set()
        assert results == ["done"] * 3
        assert (lane.stats.admitted, lane.stats.busy) == (0, 0)
        assert await lane.run(lambda: 7) == 7  # capacity is back

    anyio.run(main)


def test_a_request_past_its_deadline_leaves_but_its_thread_keeps_the_slot_until_it_ends():
    lane = Lane("heavy", threads=1, queue=1)
    release, started = threading.Event(), threading.Event()

    def slow():
        started.set()
        release.wait(10)

    async def main():
        with lanes.deadline(0.2), pytest.raises(TimeoutError):
            with anyio.fail_after(0.2):  # the middleware's cancellation at the deadline
                await lane.run(slow)
        assert started.is_set() and lane.stats.busy == 1  # the abandoned thread still works
        with lanes.deadline(0.2), pytest.raises(DeadlineExceeded, match="waited for a heavy thread"):
            await lane.run(lambda: None)  # waits for the one slot, then gives up at its deadline
        assert lane.stats.expired == 1
        release.set()
        await anyio.sleep(0.1)
        assert (lane.stats.busy, lane.stats.admitted) == (0, 0)
        assert await lane.run(lambda: "free") == "free"

    anyio.run(main)


def test_a_light_step_hands_heavy_work_on_and_work_sees_its_deadline():
    both = Lanes(light_threads=1, light_queue=0, heavy_threads=1, heavy_queue=0)
    seen = {}

    def heavy_work():
        seen["heavy_thread"] = threading.current_thread().name
        seen["left"] = lanes.remaining()
        return "heavy result"

    def light_step():
        seen["light_thread"] = threading.current_thread().name
        return Heavy(heavy_work)

    async def main():
        with lanes.deadline(50):
            return await both.run(light_step)

    assert anyio.run(main) == "heavy result"
    assert 0 < seen["left"] <= 50  # the deadline travelled into the worker thread
    assert both.light.stats.admitted == both.heavy.stats.admitted == 0


def test_check_raises_only_past_the_deadline():
    lanes.check()  # no deadline: never
    with lanes.deadline(60):
        lanes.check()
        assert 59 < lanes.remaining() <= 60
        with lanes.deadline(-1):
            with pytest.raises(DeadlineExceeded):
                lanes.check()
        lanes.check()  # the outer deadline again


def test_lane_threads_run_below_the_event_loop_so_health_and_refreshes_come_first():
    here = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    lane = Lane("light", threads=1, queue=0)

    async def main():
        return await lane.run(lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    assert anyio.run(main) == max(here, lanes.NICE)
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == here  # the caller's is kept


def test_a_step_that_must_wait_waits_without_a_lane_thread_then_steps_again():
    both = Lanes(light_threads=1, light_queue=0, heavy_threads=1, heavy_queue=0, waiters=2)
    ready, names, steps = threading.Event(), {}, []

    def wait():
        names["wait"] = threading.current_thread().name
        assert both.light.stats.busy == 0  # the light lane's one thread is free meanwhile
        ready.wait(10)

    def step():
        steps.append(ready.is_set())
        return "answer" if ready.is_set() else Waiting(wait, step)

    async def main():
        async with anyio.create_task_group() as tg:
            results = []

            async def call():
                results.append(await both.run(step))

            tg.start_soon(call)
            await anyio.sleep(0.1)
            assert both.waiting.stats.busy == 1
            assert await both.run(lambda: "light meanwhile") == "light meanwhile"
            ready.set()
        return results

    assert anyio.run(main) == ["answer"] and steps == [False, True]


def test_writes_take_turns_without_holding_a_thread_so_queries_keep_one():
    """Two writes and a query in a light lane of two threads: the second write waits for its
    turn without a thread at work, so the query runs while the first write holds."""
    all_lanes = Lanes(light_threads=2, light_queue=8, heavy_threads=1, heavy_queue=1)
    release, writing = threading.Event(), threading.Semaphore(0)
    order = []

    def write(k):
        def step():
            order.append(f"write {k}")
            writing.release()
            release.wait(10)
            return k

        return step

    async def main():
        results = []

        async def call(step, write_):
            results.append(await all_lanes.run(step, write=write_))

        async with anyio.create_task_group() as tg:
            tg.start_soon(call, write(1), True)
            await anyio.to_thread.run_sync(writing.acquire)
            tg.start_soon(call, write(2), True)
            await anyio.sleep(0.05)
            assert (all_lanes.light.stats.admitted, all_lanes.light.stats.busy) == (
                2,
                1,
            )  # 2 waits, no thread
            assert await all_lanes.run(lambda: "query") == "query"  # the free thread answers it
            assert order == ["write 1"]
            release.set()
        assert sorted(results, key=str) == [1, 2] and order == ["write 1", "write 2"]
        assert (all_lanes.light.stats.admitted, all_lanes.light.stats.busy) == (0, 0)

    anyio.run(main)


def test_on_a_local_store_reads_run_on_the_event_loop_and_writes_heavy_work_and_waits_do_not():
    """``inline``: a light read runs in the event loop's thread (counted in the light lane
    meanwhile), and again after a wait; a write, heavy work, the wait itself, the long work
    a read hands on (:class:`Threaded`) and a read of a large body run in threads; a read
    past its deadline does not start."""
    both = Lanes(light_threads=1, light_queue=0, heavy_threads=1, heavy_queue=0, inline=True)
    seen = []

    def where(what):
        seen.append((what, threading.current_thread() is threading.main_thread()))
        return what

    def read():
        where("read")
        assert (both.light.stats.admitted, both.light.stats.busy) == (1, 1) and lanes.on_loop()
        return "answer"

    waited = []

    def step():
        where("step")
        if waited:
            return Heavy(lambda: where("heavy"))
        return Waiting(lambda: waited.append(where("wait")), step)

    async def main():
        assert await both.run(read) == "answer"
        assert await both.run(step) == "heavy"
        assert await both.run(lambda: where("write"), write=True) == "write"
        assert await both.run(lambda: Threaded(lambda: where("long") if not lanes.on_loop() else 0)) == "long"
        assert await both.run(lambda: where("big body"), body_bytes=lanes.INLINE_BODY_BYTES + 1) == "big body"
        with lanes.deadline(-1), pytest.raises(DeadlineExceeded):
            await both.run(lambda: where("late"))

    anyio.run(main)
    assert seen == [
        ("read", True),
        ("step", True),
        ("wait", False),
        ("step", True),
        ("heavy", False),
        ("write", False),
        ("long", False),
        ("big body", False),
    ]
    assert both.light.stats.admitted == both.light.stats.busy == 0


def test_an_inline_read_is_shed_at_once_when_the_process_answers_more_than_the_lane_holds():
    """The event loop is the inline lane's one thread: with ``threads + queue`` requests
    being answered besides this one, a read is refused (503) without running; writes still
    queue for their turn."""
    both = Lanes(light_threads=1, light_queue=2, heavy_threads=1, heavy_queue=0, inline=True)
    ran = []

    async def main():
        for _ in range(4):  # 1 thread + 2 waiting: the lane is full, and this request beyond
            lanes.received()
        try:
            with pytest.raises(Overloaded):
                await both.run(lambda: ran.append("read"))
            assert await both.run(lambda: ran.append("write") or "written", write=True) == "written"
        finally:
            lanes.answered()
        try:
            assert await both.run(lambda: ran.append("read") or "answer") == "answer"
        finally:
            for _ in range(3):
                lanes.answered()

    anyio.run(main)
    assert ran == ["write", "read"] and both.light.stats.shed == 1


def test_an_inline_read_whose_client_left_is_dropped_before_it_runs():
    """After an overload the loop does not compute answers nobody waits for (a threaded
    read, already handed to its thread, still runs)."""
    both = Lanes(light_threads=1, light_queue=2, heavy_threads=1, heavy_queue=0, inline=True)
    ran = []

    async def main():
        with lanes.client(lambda: True):
            with pytest.raises(Overloaded):
                await both.run(lambda: ran.append("left"))
            assert await both.run(lambda: ran.append("write") or "written", write=True) == "written"
        with lanes.client(lambda: False):
            assert await both.run(lambda: ran.append("here") or "answer") == "answer"

    anyio.run(main)
    assert ran == ["write", "here"]
