"""Crazyflie link layers: CRTP packets (:mod:`.crtp`), CPX serial framing (:mod:`.cpx_serial`)
and CRTP over UDP (:mod:`.udp`). Transport below protocol; nothing here knows about the app."""

from polycc.link.crtp import MAX_PAYLOAD, CrtpPacket, FramingError, Port

__all__ = ["MAX_PAYLOAD", "CrtpPacket", "FramingError", "Port"]
