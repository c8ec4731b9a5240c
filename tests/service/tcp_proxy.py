"""A TCP proxy that can pause: a database that stops answering without closing anything
(a stalled server, a network path that drops packets), for the isolation tests."""

from __future__ import annotations

import contextlib
import select
import socket
import threading


class PausableProxy:
    """Forwards 127.0.0.1:``port`` to ``target`` (host, port). While :meth:`pause` holds,
    bytes are neither read nor forwarded in either direction (connections stay open);
    :meth:`resume` lets them through again. ``stop`` closes everything."""

    def __init__(self, target: tuple[str, int], port: int = 0):
        self.target = target
        self._listener = socket.create_server(("127.0.0.1", port))
        self.port = self._listener.getsockname()[1]
        self._running = threading.Event()
        self._running.set()
        self._closed = False
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    def stop(self) -> None:
        self._closed = True
        self._running.set()
        with contextlib.suppress(OSError):
            self._listener.close()
        with self._lock:
            for sock in self._sockets:
                with contextlib.suppress(OSError):
                    sock.close()

    def _accept(self) -> None:
        while not self._closed:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            try:
                server = socket.create_connection(self.target, timeout=5)
            except OSError:
                client.close()
                continue
            with self._lock:
                self._sockets += [client, server]
            threading.Thread(target=self._pump, args=(client, server), daemon=True).start()

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        peer = {a: b, b: a}
        try:
            while not self._closed:
                self._running.wait()
                ready, _, _ = select.select([a, b], [], [], 0.05)
                if not self._running.is_set():
                    continue  # paused while waiting: hold what arrived
                for sock in ready:
                    data = sock.recv(65536)
                    if not data:
                        return
                    peer[sock].sendall(data)
        except (OSError, ValueError):  # closed by stop(), or by the other side
            return
        finally:
            for sock in (a, b):
                with contextlib.suppress(OSError):
                    sock.close()
