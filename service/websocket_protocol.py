"""uvicorn's WebSocket protocol with two changes: a client that does not answer a ping in time is closed with 1008
and a reason, and the connection lingers so that the reason can reach it; and a text message that is not UTF-8 is
closed with 1007 and a reason that says where, logged in one line and lingering alike (uvicorn closes it with no
reason and logs two tracebacks, its own close raising on a connection the WebSocket library is already closing).

A client that stops reading its socket stops answering pings too, while the kernel's buffers (megabytes on
loopback) still take everything the service sends: the ping is the first sign that it has fallen behind. uvicorn
then writes a 1011 close frame and closes the socket at once; a client that is still sending gets a reset, and the
close frame, still unread in its buffer, is lost with it ("cut off with no reason"). Here the close frame (1008,
the reason) is followed by a half-close: the service sends nothing more but goes on reading, and throwing away,
what the client sends, until the client answers the close or ``LINGER_S`` passes. A client that reads again gets
what was queued, then the reason. (The service's own outbox watchdog, ``service.api.outbox``, closes the clients
whose buffers did fill.)
"""

from __future__ import annotations

from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.protocol import State

LINGER_S = 60.0


class WebSocketProtocol(WebSocketsSansIOProtocol):
    def keepalive_timeout(self) -> None:
        self.pong_timer = None
        self.pending_ping_payload = None
        if self.close_sent or self.transport.is_closing():
            return
        self._close_lingering(
            1008, f"consumer too slow: no answer to a ping within {self.ping_timeout:g} s (not reading)"
        )

    def send_receive_event_to_app(self) -> None:
        if self.curr_msg_data_type == "text" and not self.close_sent:
            try:
                b"".join(self.frames).decode()
            except UnicodeDecodeError as exc:
                self.frames = []
                self._close_lingering(
                    1007, f"a text message must be UTF-8 JSON; byte {exc.start} is not UTF-8 ({exc.reason})"
                )
                return
        super().send_receive_event_to_app()

    def _close_lingering(self, code: int, reason: str) -> None:
        """Tell the app, send the close frame with ``reason``, then half-close and go on reading (and discarding)
        until the client answers the close or ``LINGER_S`` passes, so that the reason reaches a client still
        sending."""
        self.logger.info("closing a WebSocket client with %d: %s", code, reason)
        self.queue.put_nowait({"type": "websocket.disconnect", "code": code, "reason": reason})
        if self.conn.state is State.OPEN:
            self.conn.send_close(code, reason)
        self.transport.write(b"".join(self.conn.data_to_send()))
        self.close_sent = True
        if self.read_paused:
            self.read_paused = False
            self.transport.resume_reading()
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.close_timer = self.loop.call_later(max(self.close_timeout, LINGER_S), self.transport.close)
