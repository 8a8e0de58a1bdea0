"""Errors raised by the codecs. Drivers translate them into ``drivers.errors.ProtocolError``."""
from __future__ import annotations


class FrameError(ValueError):
    """Bytes that do not form a valid message of the protocol."""


class CrcError(FrameError):
    """A frame whose checksum does not match its contents."""


class TruncatedFrameError(FrameError):
    """A frame shorter than its header or declared length."""
