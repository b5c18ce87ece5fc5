"""asyncio: `async for` over a subscription, `await` on receives and
calls, `async def` handlers, cancelling, and a thread publishing meanwhile."""

import asyncio
import threading
import time

import pytest

import pulicast_rs
from conftest import WAIT


def test_async_receive_and_calls(make_node):
    server = make_node("py_server")

    @server.serve("slow_double")
    async def slow_double(x: int) -> int:
        await asyncio.sleep(0.01)
        return 2 * x

    node = make_node("py_async")
    numbers = node.channel("numbers")
    talker = make_node("talker").channel("numbers")

    async def main():
        sub = numbers.subscribe()
        assert await sub.recv_async(timeout=0.05) is None  # nothing yet
        stop = threading.Event()

        def publish():
            i = 0
            while not stop.is_set() and i < 10_000:
                talker.publish(i)
                i += 1
                time.sleep(0.002)

        thread = threading.Thread(target=publish)
        thread.start()
        got = []
        try:
            async for message in sub:
                got.append(message.value)
                if len(got) == 20:
                    break
        finally:
            stop.set()
            thread.join()
        assert got == sorted(got) and len(got) == 20

        client = node.client("slow_double")
        # Several calls at once, on one event loop.
        replies = await asyncio.gather(*(client.call_async(i, timeout=WAIT) for i in range(5)))
        assert replies == [0, 2, 4, 6, 8]
        with pytest.raises(pulicast_rs.PulicastError, match="no server of nobody"):
            await node.client("nobody").call_async(1, timeout=0.2)

        # Cancelling a receive leaves the subscription usable.
        while await sub.recv_async(timeout=0.2) is not None:
            pass  # what the loop above left queued
        waiting = asyncio.ensure_future(sub.recv_async())
        await asyncio.sleep(0.05)
        assert not waiting.done()
        waiting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiting
        # (A message that arrives as the receive is cancelled may go with
        # it: docs/python.md. This one comes after.)
        await asyncio.sleep(0.05)
        talker.publish(-1)
        message = await sub.recv_async(timeout=WAIT)
        while message is not None and message.value != -1:
            message = await sub.recv_async(timeout=WAIT)
        assert message is not None and message.value == -1

        # The iteration ends when the subscription is closed.
        async def drain():
            return [m async for m in sub]

        draining = asyncio.ensure_future(drain())
        await asyncio.sleep(0.05)
        sub.close()
        await asyncio.wait_for(draining, WAIT)

    asyncio.run(main())


def test_settings_progress_and_discovery_events_are_awaitable(make_node):
    owner = make_node("owner", "rover1")
    speed = owner.setting("max_speed", 1.5, range=(0, 2))

    def count(n: int, call) -> int:
        for i in range(n):
            call.progress(i)
            time.sleep(0.01)
        return n

    counter = owner.serve("count", count, request=int, reply=int, progress=int)
    node = make_node("py_async")
    events = node.discovery_events()

    async def main():
        # Discovery: a node that joins now is seen, by `async for` too.
        make_node("late_joiner")

        async def joined():
            async for event in events:
                if event.kind == "joined" and event.name == "late_joiner":
                    return event

        assert (await asyncio.wait_for(joined(), WAIT)).name == "late_joiner"

        # The fleet's settings.
        fleet = node.fleet_settings()
        assert (await fleet.set_async("rover1/max_speed", 1.8, timeout=WAIT)).value == 1.8
        assert speed.value == 1.8
        with pytest.raises(ValueError, match="max_speed"):
            await fleet.set_async("rover1/max_speed", 5, timeout=WAIT)
        assert (await fleet.set_text_async("rover1/max_speed", "0.5", timeout=WAIT)).value == 0.5
        assert (await fleet.reset_async("rover1/max_speed", timeout=WAIT)).value == 1.5
        assert (await fleet.get_async("rover1/max_speed", timeout=WAIT)).value == 1.5
        listed = await fleet.list_async(quiet=0.3)
        assert "rover1/max_speed" in [info.name for info in listed]

        # A call's progress and reply.
        client = node.client("rover1/count")
        call = client.start(3, timeout=WAIT)
        assert [p async for p in call] == [0, 1, 2]
        assert await call.reply_async() == 3
        call = client.start(4, timeout=WAIT)
        assert await call.progress_async() == 0
        assert await call.reply_async() == 4  # the rest of the progress skipped
        # One task reads the progress while another awaits the reply: the
        # reply comes whichever meets the end of the call.
        for _ in range(3):
            call = client.start(3, timeout=WAIT)

            async def steps(call=call):
                return [p async for p in call]

            progress, reply = await asyncio.gather(steps(), call.reply_async())
            assert reply == 3 and progress == [0, 1, 2][: len(progress)]
        # Several at once on one loop.
        calls = [client.start(2, timeout=WAIT) for _ in range(3)]
        assert await asyncio.gather(*(c.reply_async() for c in calls)) == [2, 2, 2]

    asyncio.run(main())
    counter.close()
