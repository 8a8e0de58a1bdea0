"""Byte formats only: message types, encode/decode, framing and CRCs for every device link.

No I/O and no threads live here, so the same code serves the host drivers, the loopback fakes and
(as a reference) firmware authors. Decoders raise :class:`firmware_protocol.errors.FrameError`.
"""
