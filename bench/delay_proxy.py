"""`python -m bench.delay_proxy --listen H:P --to H:P --delay-ms D`: a TCP relay that holds every
byte for D milliseconds each way, in order: a slow link where the kernel has no `tc netem`.

Each chunk read is stamped and written out once its time has come, so the relay adds latency
without capping bandwidth (beyond what this process can copy). TLS passes through untouched.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import time


async def _pump(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, delay_s: float) -> None:
    queue: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

    async def send() -> None:
        while True:
            due, chunk = await queue.get()
            if not chunk:
                break
            if (wait := due - time.monotonic()) > 0:
                await asyncio.sleep(wait)
            writer.write(chunk)
            await writer.drain()
        writer.close()

    sender = asyncio.create_task(send())
    try:
        while chunk := await reader.read(1 << 16):
            queue.put_nowait((time.monotonic() + delay_s, chunk))
    except ConnectionError:
        pass
    queue.put_nowait((0.0, b""))
    with contextlib.suppress(ConnectionError):
        await sender


async def serve(listen: tuple[str, int], to: tuple[str, int], delay_s: float) -> None:
    async def relay(client_r: asyncio.StreamReader, client_w: asyncio.StreamWriter) -> None:
        try:
            server_r, server_w = await asyncio.open_connection(*to)
        except OSError:
            client_w.close()
            return
        await asyncio.gather(_pump(client_r, server_w, delay_s), _pump(server_r, client_w, delay_s))

    server = await asyncio.start_server(relay, *listen)
    async with server:
        await server.serve_forever()


def _hostport(value: str) -> tuple[str, int]:
    host, _, port = value.rpartition(":")
    return host, int(port)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.delay_proxy", description=__doc__.split("\n\n")[0])
    p.add_argument("--listen", type=_hostport, required=True)
    p.add_argument("--to", type=_hostport, required=True)
    p.add_argument("--delay-ms", type=float, default=20.0)
    args = p.parse_args(argv)
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(args.listen, args.to, args.delay_ms / 1000.0))


if __name__ == "__main__":
    main()
