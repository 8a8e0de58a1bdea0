"""The loopback NDI tracker in process: its state machine, error replies, frame clock, noise and volume."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.loopback.ots_fake import (
    SPECTRA_BX_FIRMWARE,
    BoxVolume,
    FirmwareIdentity,
    FixedPose,
    NdiTrackerFake,
    NoiseModel,
    ScriptedPoses,
    make_default_fake,
    synthetic_rom,
)
from firmware_protocol.ndi import decode_reply, encode_command, parse_phsr, rom_chunks
from firmware_protocol.ndi_replies import PORT_OUT_OF_VOLUME, ToolState, decode_bx, decode_tx

POSE = (np.eye(3), (10.0, -20.0, -1500.0))


def talk(fake: NdiTrackerFake, name: str, params: str = "", now: float = 0.0, crc: bool = True) -> str:
    return decode_reply(fake.feed(encode_command(name, params, with_crc=crc), now))


def load(fake: NdiTrackerFake, rom: bytes = b"", *, lower: bool = False, now: float = 0.0) -> int:
    handle = int(talk(fake, "PHRQ", "*********1****", now), 16)
    for address, chunk in rom_chunks(rom or synthetic_rom()):
        assert talk(fake, "PVWR", f"{handle:02X}{address:04X}{chunk.hex().upper()}", now) == "OKAY"
    text = f"{handle:02x}" if lower else f"{handle:02X}"
    assert talk(fake, "PINIT", text, now) == "OKAY"
    assert talk(fake, "PENA", text + "D", now) == "OKAY"
    return handle


@pytest.fixture
def fake() -> NdiTrackerFake:
    device = NdiTrackerFake(FixedPose(*POSE), noise=NoiseModel(seed=7))
    assert talk(device, "INIT") == "OKAY"
    return device


def test_both_command_forms_and_init_twice(fake: NdiTrackerFake) -> None:
    assert talk(fake, "INIT", crc=False) == "OKAY"
    assert talk(fake, "COMM", "50000") == "OKAY"
    assert fake.comm.baudrate == 115200
    assert talk(fake, "BEEP", "1", crc=False) == "1"


def test_commands_split_and_batched() -> None:
    device = make_default_fake()
    wire = encode_command("INIT") + encode_command("VER", "0")
    assert device.feed(wire[:5], 0.0) == b""
    replies = device.feed(wire[5:], 0.0)
    assert replies.startswith(b"OKAYA896\r") and b"Freeze Tag: Polaris Spectra Rev 007\n" in replies


@pytest.mark.parametrize("name, params, code", [
    ("NOPE", "", "01"), ("TX", "0001", "0C"), ("BX", "", "0C"), ("TSTOP", "", "0C"),
    ("PINIT", "05", "08"), ("PINIT", "5", "07"), ("COMM", "5000", "07"), ("COMM", "90000", "06"),
    ("VER", "9", "24"), ("PHSR", "07", "24"), ("PHRQ", "***", "07"), ("TSTART", "12", "24"),
])
def test_error_replies(fake: NdiTrackerFake, name: str, params: str, code: str) -> None:
    assert talk(fake, name, params) == f"ERROR{code}"


def test_bad_crc_and_uninitialised_system() -> None:
    device = make_default_fake()
    assert decode_reply(device.feed(b"INIT:E3A6\r", 0.0)) == "ERROR04"
    assert talk(device, "PHRQ", "*********1****") == "ERROR10"
    assert talk(device, "TSTART") == "ERROR10"
    assert decode_reply(device.feed(b"X" * 1100, 0.0)) == "ERROR02"


def test_port_handle_life_cycle_errors(fake: NdiTrackerFake) -> None:
    handle = int(talk(fake, "PHRQ", "*********1****"), 16)
    h = f"{handle:02X}"
    assert talk(fake, "PINIT", h) == "ERROR0D"                 # no tool definition written yet
    assert talk(fake, "PENA", h + "D") == "ERROR0E"
    assert talk(fake, "PVWR", h + "0000" + "00" * 63) == "ERROR07"
    assert talk(fake, "PVWR", h + "0020" + "01" * 64) == "ERROR24"
    assert talk(fake, "PVWR", h + "0000" + "01" * 64) == "OKAY"
    assert talk(fake, "PINIT", h) == "OKAY"
    assert talk(fake, "PENA", h + "X") == "ERROR09"
    assert talk(fake, "PDIS", h) == "ERROR0F"
    assert talk(fake, "PENA", h + "D") == "OKAY"
    assert talk(fake, "PHF", h) == "OKAY"
    assert talk(fake, "PHF", h) == "ERROR08"


def test_handles_run_out(fake: NdiTrackerFake) -> None:
    for _ in range(fake.max_handles):
        talk(fake, "PHRQ", "*********1****")
    assert talk(fake, "PHRQ", "*********1****") == "ERROR2D"


def test_rom_stored_exactly_and_lowercase_handles(fake: NdiTrackerFake) -> None:
    device = NdiTrackerFake(FixedPose(*POSE), first_handle=0x0A)
    talk(device, "INIT")
    rom = synthetic_rom("ROM-UNDER-TEST")
    handle = load(device, rom, lower=True)
    assert handle == 0x0A
    assert bytes(device.ports[handle].rom) == rom.ljust(1024, b"\0")
    assert device.ports[handle].chunks_written == set(range(0, 1024, 64))


def test_phsr_modes(fake: NdiTrackerFake) -> None:
    enabled = load(fake)
    fresh = int(talk(fake, "PHRQ", "*********1****"), 16)
    assert [e.handle for e in parse_phsr(talk(fake, "PHSR", "00"))] == [enabled, fresh]
    assert parse_phsr(talk(fake, "PHSR", "01")) == []
    assert [e.handle for e in parse_phsr(talk(fake, "PHSR", "02"))] == [fresh]
    assert [(e.handle, e.status) for e in parse_phsr(talk(fake, "PHSR", "04"))] == [(enabled, 0x031)]


def test_tracking_reply_frame_clock_and_repeatability(fake: NdiTrackerFake) -> None:
    handle = load(fake)
    assert talk(fake, "TSTART", now=0.0) == "OKAY"
    first = fake.feed(encode_command("TX", "0001"), 1.0)
    again = fake.feed(encode_command("TX", "0001"), 1.0 + 0.1 / 60)   # same 60 Hz frame
    later = fake.feed(encode_command("TX", "0001"), 1.0 + 1.5 / 60)
    assert first == again != later
    tool = decode_tx(first).tools[0]
    assert (tool.handle, tool.state, tool.frame, tool.port_status) == (handle, ToolState.VALID, 60, 0x31)
    assert decode_tx(later).tools[0].frame == 61
    assert talk(fake, "TSTOP", now=2.0) == "OKAY"
    assert talk(fake, "TSTART", "80", now=2.0) == "OKAY"            # reset the frame counter
    assert decode_tx(fake.feed(encode_command("TX"), 2.5)).tools[0].frame == 30


def test_noise_matches_polaris_accuracy() -> None:
    device = NdiTrackerFake(FixedPose(*POSE), noise=NoiseModel(position_rms_mm=0.19, seed=3))
    talk(device, "INIT")
    load(device)
    talk(device, "TSTART")
    positions = []
    for n in range(600):
        tool = decode_bx(device.feed(encode_command("BX", "0001"), n / 60.0)).tools[0]
        positions.append(tool.translation_mm)
        assert abs(np.linalg.norm(tool.quaternion) - 1) < 1e-5 and tool.quaternion[0] >= 0
    error = np.asarray(positions) - POSE[1]
    rms = float(np.sqrt(np.mean(np.sum(error ** 2, axis=1))))
    assert 0.17 < rms < 0.21
    assert np.all(np.abs(error.mean(axis=0)) < 4 * 0.11 / np.sqrt(600))


def test_seeded_fakes_repeat_each_other() -> None:
    def run() -> bytes:
        device = make_default_fake(seed=11)
        talk(device, "INIT")
        load(device)
        talk(device, "TSTART")
        return b"".join(device.feed(encode_command("TX"), n / 60.0) for n in range(5))

    assert run() == run()


def test_outside_the_volume_is_missing_unless_option_0800(fake: NdiTrackerFake) -> None:
    fake.provider = FixedPose(np.eye(3), (0.0, 0.0, -3000.0))      # behind the far end of the volume
    handle = load(fake)
    talk(fake, "TSTART")
    missing = decode_tx(fake.feed(encode_command("TX", "0001"), 0.5)).tools[0]
    assert (missing.handle, missing.state, missing.quaternion) == (handle, ToolState.MISSING, None)
    flagged = decode_tx(fake.feed(encode_command("TX", "0801"), 0.5)).tools[0]
    assert flagged.state == ToolState.VALID and flagged.port_status & PORT_OUT_OF_VOLUME
    assert BoxVolume().contains(np.array([0, 0, -1500.0])) and not BoxVolume().contains(np.array([0, 0, -500.0]))
    assert talk(fake, "TX", "0002") == "ERROR24"


def test_scripted_poses_missing_tools_and_disabled_handles() -> None:
    quarter_turn_z = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    script = ScriptedPoses([(0.0, {0: (quarter_turn_z, (0, 0, -1200)), 1: None}),
                            (1.0, {0: None, 1: ((1, 0, 0, 0), (5, 5, -1300))})])
    device = NdiTrackerFake(script, noise=NoiseModel(position_rms_mm=0.0, rotation_rms_deg=0.0, seed=1))
    talk(device, "INIT")
    first, second = load(device), load(device)
    talk(device, "TSTART")
    early = decode_tx(device.feed(encode_command("TX"), 0.5)).by_handle()
    assert early[first].state == ToolState.VALID and early[second].state == ToolState.MISSING
    assert early[first].quaternion == pytest.approx((np.sqrt(0.5), 0, 0, np.sqrt(0.5)), abs=1e-4)
    assert early[first].translation_mm == (0.0, 0.0, -1200.0)
    late = decode_tx(device.feed(encode_command("TX"), 1.5)).by_handle()
    assert late[first].state == ToolState.MISSING and late[second].translation_mm == (5.0, 5.0, -1300.0)
    assert talk(device, "PDIS", f"{second:02X}", now=1.5) == "OKAY"
    assert decode_tx(device.feed(encode_command("TX"), 1.6)).by_handle()[second].state == ToolState.DISABLED


def test_version_text_and_getinfo() -> None:
    tx_fake, bx_fake = make_default_fake(), NdiTrackerFake(FixedPose(*POSE), firmware=SPECTRA_BX_FIRMWARE)
    assert "Freeze Tag: Polaris Spectra Rev 007\n" in talk(tx_fake, "VER", "0")
    assert "Freeze Tag: Polaris Spectra Rev 010\n" in talk(bx_fake, "VER", "0")
    assert talk(tx_fake, "GETINFO", "Features.Firmware.Version").startswith("Features.Firmware.Version=007.")
    old = NdiTrackerFake(FixedPose(*POSE), firmware=FirmwareIdentity(getinfo=False))
    assert talk(old, "GETINFO", "Features.Firmware.Version") == "ERROR01"


def test_never_unsolicited_and_reset(fake: NdiTrackerFake) -> None:
    load(fake)
    talk(fake, "TSTART")
    assert all(fake.tick(t / 10) == b"" for t in range(50))
    assert talk(fake, "RESET", "0") == "RESET"
    assert not fake.ports and not fake.tracking and not fake.initialised


def test_nine_tools_fit_in_one_reply(fake: NdiTrackerFake) -> None:
    for _ in range(9):
        load(fake)
    talk(fake, "TSTART")
    wire = fake.feed(encode_command("TX"), 0.1)
    assert len(decode_tx(wire).tools) == 9 and len(wire) < 2047


def test_default_fake_pose_argument() -> None:
    device = make_default_fake((1, 2, -1000, 2, 0, 0, 0), seed=0)   # quaternion normalised
    device.noise = NoiseModel(position_rms_mm=0.0, rotation_rms_deg=0.0)
    talk(device, "INIT")
    load(device)
    talk(device, "TSTART")
    tool = decode_tx(device.feed(encode_command("TX"), 0.0)).tools[0]
    assert tool.translation_mm == (1.0, 2.0, -1000.0) and tool.quaternion == (1.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="7 numbers"):
        make_default_fake((1, 2, 3))


_command_names = st.sampled_from(["INIT", "TX", "BX", "PHRQ", "PVWR", "PINIT", "PENA", "PDIS", "PHF", "PHSR",
                                  "TSTART", "TSTOP", "COMM", "VER", "GETINFO", "BEEP", "RESET", "XYZ"])
_params = st.text(alphabet="0123456789ABCDEFabcdef*:. ", max_size=140)


@settings(max_examples=120, deadline=None)
@given(st.lists(st.one_of(st.tuples(_command_names, _params, st.booleans()),
                          st.binary(max_size=40).map(lambda raw: raw.replace(b"\r", b"") + b"\r")), max_size=25))
def test_any_input_gets_well_formed_replies_only(inputs: list[object]) -> None:
    device = make_default_fake(seed=0)
    now = 0.0
    for item in inputs:
        now += 0.01
        wire = encode_command(*item[:2], with_crc=item[2]) if isinstance(item, tuple) else item
        reply = device.feed(wire, now)
        assert device.tick(now) == b""
        if wire.strip(b"\r\n") == b"":
            assert reply == b""          # a bare line end is not a command: nothing to answer
        elif reply[:1] == b"\xc4":
            decode_bx(reply)
        else:
            assert reply.endswith(b"\r") and reply.count(b"\r") == 1, reply
            decode_reply(reply)
