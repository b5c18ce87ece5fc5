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
