"""Thousands of SET_CURRENTS exchanges over a link that flips bits, drops bytes and whole frames,
truncates, inserts noise and duplicates frames, both ways. The host side retransmits like the driver
(same bytes, same sequence number). Checked: no command is ever applied with a value the host did not
send for that sequence number, none is applied twice, none out of order; and every frame that reached
a decoder is either accepted or counted as rejected under a reason.

The fake is driven in-process through the codec on a synthetic clock: the pty is not the point here
(the driver-over-pty noise test is in tests/drivers/test_amplifier_pty.py)."""
from __future__ import annotations

import random
from collections import Counter

from drivers.loopback.amplifier_fake import FakeAmplifier, FakeAmplifierConfig
from firmware_protocol.amplifier import (
    Enable,
    Hello,
    MessageDecoder,
    SetCurrents,
    SetCurrentsReply,
    encode_message,
)

COMMANDS = 3000
CHANNELS = 8
MAX_ATTEMPTS = 40
_OPS = ["pass", "flip", "flips", "drop_bytes", "drop_frame", "duplicate", "truncate", "insert"]
_WEIGHTS = [55, 10, 5, 8, 8, 6, 4, 4]


class Link:
    """One direction of a bad line; remembers what it delivered so the rejections can be audited."""

    def __init__(self, rng: random.Random) -> None:
        self.rng = rng
        self.delivered = bytearray()
        self.ops: Counter[str] = Counter()

    def carry(self, frame: bytes) -> bytes:
        if not frame:
            return b""
        rng = self.rng
        op = rng.choices(_OPS, _WEIGHTS)[0]
        self.ops[op] += 1
        data = bytearray(frame)
        if op == "flip":
            i = rng.randrange(len(data))
            data[i] ^= 1 << rng.randrange(8)
        elif op == "flips":
            for _ in range(rng.randint(2, 8)):
                i = rng.randrange(len(data))
                data[i] ^= 1 << rng.randrange(8)
        elif op == "drop_bytes":
            for _ in range(rng.randint(1, 3)):
                del data[rng.randrange(len(data))]
        elif op == "drop_frame":
            data = bytearray()
        elif op == "duplicate":
            data = data + data
        elif op == "truncate":
            data = data[:rng.randrange(1, len(data))]
        elif op == "insert":
            i = rng.randrange(len(data) + 1)
            data[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 6)))
        self.delivered += data
        return bytes(data)

    def segments(self) -> int:
        """Non-empty runs between delimiters: each is one frame a decoder must accept or reject."""
        return sum(1 for part in bytes(self.delivered).split(b"\x00") if part)


def test_corrupted_link_never_applies_a_wrong_value_and_accounts_for_every_frame() -> None:
    rng = random.Random(20261121)
    fake = FakeAmplifier(FakeAmplifierConfig(channels=CHANNELS, watchdog_ms=500))
    host = MessageDecoder()
    t = 0.0
    fake.tick(t)
    # Session start over a clean line.
    for seq, request in ((1, Hello()), (2, Enable())):
        host.feed(fake.feed(encode_message(request, seq), t))
    to_fake, to_host = Link(rng), Link(rng)
    sent: dict[int, tuple[int, ...]] = {}
    acked = given_up = discarded = 0
    seq = 2
    for _ in range(COMMANDS):
        seq = (seq + 1) & 0xFFFF
        currents = tuple(rng.randint(-10_000, 10_000) for _ in range(CHANNELS))
        sent[seq] = currents
        frame = encode_message(SetCurrents(currents), seq)
        for _attempt in range(MAX_ATTEMPTS):
            t += 0.001
            replies = host.feed(to_host.carry(fake.feed(to_fake.carry(frame), t)))
            mine = [r for r in replies if r.seq == seq and isinstance(r.message, SetCurrentsReply)]
            discarded += len(replies) - len(mine)
            if mine:
                acked += 1
                break
        else:
            given_up += 1
    # End of stream: a delimiter closes any partial frame so it is counted too.
    fake.feed(b"\x00", t)
    host.feed(b"\x00")

    print(f"\nlink ops to amplifier {dict(to_fake.ops)}, to host {dict(to_host.ops)}; "
          f"amplifier rejected {dict(fake.decoder.rejected)}, host rejected {dict(host.rejected)}; "
          f"applied {len(fake.applied)}, duplicates answered from cache {fake.duplicates}, "
          f"replies discarded by the host {discarded}")
    applied = list(fake.applied)
    wrong = [a for a in applied if sent.get(a.seq) != a.requested_ma]
    assert wrong == [], f"{len(wrong)} commands applied with values the host never sent for that seq"
    seqs = [a.seq for a in applied]
    assert seqs == sorted(set(seqs)), "a command was applied twice or out of order"
    assert acked + given_up == COMMANDS and given_up == 0
    # Every acknowledged command was applied (an ack is only sent after applying).
    assert len(applied) >= acked

    # Accounting: every frame a decoder saw is accepted or rejected under a named reason (the two
    # session-start frames did not cross the bad link).
    assert fake.decoder.accepted - 2 + fake.decoder.rejected_total == to_fake.segments()
    assert host.accepted - 2 + host.rejected_total == to_host.segments()
    assert fake.decoder.rejected_total > 1000 and host.rejected_total > 1000
    assert all(fake.decoder.rejected[reason] > 0 for reason in ("crc", "cobs", "truncated", "length"))
    assert fake.duplicates > 0   # lost replies made the host retransmit commands already applied
