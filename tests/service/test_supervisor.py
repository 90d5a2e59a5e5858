"""How the service's processes listen and stop: the workers' sockets (service.supervisor) and the
server's graceful shutdown (service.protocol.ServiceServer), without starting a service."""

import asyncio
import socket

import uvicorn

from service.protocol import ServiceServer
from service.supervisor import listening_sockets


def test_each_worker_gets_a_socket_on_one_port_whose_connections_send_at_once():
    sockets = listening_sockets("127.0.0.1", 0, 3)

    async def nodelay_of_accepted() -> list[int]:
        loop = asyncio.get_running_loop()
        accepted: asyncio.Queue = asyncio.Queue()

        class Accepted(asyncio.Protocol):
            def connection_made(self, transport):
                accepted.put_nowait(
                    transport.get_extra_info("socket").getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY)
                )

        servers = [await loop.create_server(Accepted, sock=sock) for sock in sockets]
        clients = [await asyncio.open_connection("127.0.0.1", sockets[0].getsockname()[1]) for _ in range(6)]
        flags = [await asyncio.wait_for(accepted.get(), 10) for _ in clients]
        for _, writer in clients:
            writer.close()
        for server in servers:
            server.close()
        return flags

    try:
        assert len(sockets) == 3 and len({sock.getsockname() for sock in sockets}) == 1
        assert all(sock.get_inheritable() for sock in sockets)  # the workers are spawned, not forked
        # Nagle's algorithm would hold each answer's last segment for the client's delayed ACK (40 ms).
        assert all(flag != 0 for flag in asyncio.run(nodelay_of_accepted()))
    finally:
        for sock in sockets:
            sock.close()


def test_a_connection_that_opens_during_the_shutdown_is_asked_to_close():
    # Accepted just before the listeners closed, its protocol started after uvicorn asked the open
    # connections to close: it served its client until the graceful timeout cancelled its request.
    server = ServiceServer(uvicorn.Config(app=None, timeout_graceful_shutdown=5))
    server.servers = []

    class Lifespan:
        async def shutdown(self):
            pass

    class Connection:
        asked = False

        def shutdown(self):
            self.asked = True
            server.server_state.connections.discard(self)  # closes once its answer is out

    server.lifespan = Lifespan()
    latecomer = Connection()

    async def shut_down_as_a_connection_opens() -> float:
        started = asyncio.get_running_loop().time()
        shutdown = asyncio.create_task(server.shutdown())
        await asyncio.sleep(0.02)
        server.server_state.connections.add(latecomer)
        await shutdown
        return asyncio.get_running_loop().time() - started

    seconds = asyncio.run(shut_down_as_a_connection_opens())
    assert latecomer.asked and seconds < 2  # not held until the graceful timeout (5 s)
