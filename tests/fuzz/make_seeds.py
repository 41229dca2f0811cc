#!/usr/bin/env python3
"""Writes the seed corpora of tests/fuzz/corpus/: the protocol's from tests/protocol/golden_vectors.txt,
igtl and udp from the formats in docs/sources.md.

    python3 tests/fuzz/make_seeds.py

Input formats are those of tests/fuzz/fuzz_entry.hpp and fuzz_sources.hpp. Rerun after the golden
vectors change.
"""
import pathlib
import struct

ROOT = pathlib.Path(__file__).resolve().parent
GOLDEN = ROOT.parent / "protocol" / "golden_vectors.txt"
CORPUS = ROOT / "corpus"
NODE_BYTE = 4  # decoder node = 1 + byte % 15 = 5, the golden vectors' node


def golden():
    vectors = {}
    for line in GOLDEN.read_text().splitlines():
        if not line or line.startswith("#"):
            continue
        name, framing, *tokens = line.split()
        vectors[(name, framing)] = tokens
    return vectors


def frame(token):
    ident, _, data = token.partition("#")
    fd = data.startswith("#")
    if fd:
        data = data[2:]  # '#' and the flags nibble
    return int(ident, 16), fd, bytes.fromhex(data)


def classic_record(token, flags=0):
    ident, _, data = frame(token)
    return bytes([flags]) + struct.pack("<H", ident) + bytes([len(data)]) + data


def fd_record(token, flags=1):
    ident, _, data = frame(token)
    return bytes([flags]) + struct.pack("<H", ident) + bytes([len(data)]) + data


def write(decoder, name, data):
    folder = CORPUS / decoder
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_bytes(data)


def main():
    v = golden()
    for name in ["heartbeat", "valve_currents", "telemetry", "identity", "cell_targets", "config_data", "usb_slots",
                 "sensor_deadband"]:
        write("packet", name, bytes.fromhex(v[(name, "packet")][0]))
    report = bytes.fromhex(v[("status", "packet")][0])
    write("packet", "status_hid_report", report + bytes(64 - len(report)))
    # Protocol 1.2 packed reports: as the report's bytes and as a zero-padded HID report.
    for name in ["packed_host_report", "packed_device_report"]:
        report = bytes.fromhex(v[(name, "report")][0])
        write("packet", name, report)
        write("packet", name + "_hid", report + bytes(64 - len(report)))
    # A high-speed unit's 1024-byte report (UsbSlots): packed device reports back to back.
    device = bytes.fromhex(v[("packed_device_report", "report")][0])
    big = device * (1024 // len(device))
    write("packet", "packed_report_1024", big + bytes(1024 - len(big)))
    v2 = bytearray(bytes.fromhex(v[("heartbeat", "packet")][0]))
    v2[0] = 2
    write("packet", "version2_heartbeat", bytes(v2))

    for name in ["valve_currents", "valve_currents_partial", "telemetry", "cell_targets", "identity", "config_write"]:
        write("can_classic", name, bytes([NODE_BYTE]) + b"".join(classic_record(t) for t in v[(name, "can")]))
    mgmt = b"".join(classic_record(v[(n, "can")][0]) for n in ["heartbeat", "status", "time_sync", "state_request"])
    write("can_classic", "management", bytes([NODE_BYTE]) + mgmt)

    for name in ["valve_currents", "telemetry", "identity", "heartbeat", "config_ack"]:
        write("can_fd", name, bytes([NODE_BYTE]) + fd_record(v[(name, "canfd")][0]))
    for name in ["packed_host_report", "packed_device_report"]:
        write("can_fd", name, bytes([NODE_BYTE]) + fd_record(v[(name, "canfd")][0]))
    write("can_fd", "classic_and_fd", bytes([NODE_BYTE]) + fd_record(v[("status", "can")][0], flags=0) +
          fd_record(v[("status", "canfd")][0]))

    def quantize(value, lsb, max_u, lo, hi, lsb_na, max_c, lsb_nano, extra1, extra2):
        return struct.pack("<ddHhhIHIdd", value, lsb, max_u, lo, hi, lsb_na, max_c, lsb_nano, extra1, extra2)
    write("quantize", "current_0p25A", quantize(0.25, 125e-6, 4000, -2048, 2047, 125000, 4000, 2500, 1e-3, 0.1))
    write("quantize", "sensor_negative", quantize(-2.5e-3, 2.5e-6, 4095, -2048, 2047, 1000, 4095, 2500, 1.0, 0.63))
    write("quantize", "nan", quantize(float("nan"), 1.0, 100, -100, 100, 1, 1, 1, 0.0, 0.0))
    write("quantize", "inf", quantize(float("inf"), 1.0, 100, -100, 100, 1, 1, 1, float("-inf"), 0.0))
    write("quantize", "denormal_lsb", quantize(1e-320, 5e-324, 65535, -32768, 32767, 0, 0, 0, 0.0, 0.0))
    write("quantize", "half_lsb_edges", quantize(4095.5, 1.0, 4095, -2048, 2047, 1, 4095, 1, 8.191e-3, 0.635))

    igtl_seeds()
    udp_seeds()


# ---- stream sources (tests/fuzz/fuzz_sources.hpp) ----------------------------------------------

def crc64_ecma(data):
    """CRC-64/ECMA-182 as OpenIGTLink's crc64(data, len, 0): not reflected, init 0."""
    crc = 0
    for b in data:
        crc ^= b << 56
        for _ in range(8):
            crc = ((crc << 1) ^ 0x42F0E1EBA9EA3693) if crc & (1 << 63) else crc << 1
            crc &= (1 << 64) - 1
    return crc


def igtl(msg_type, device, body, version=1, stamp_s=1.5, crc=None, body_bytes=None):
    """An OpenIGTLink message: 58-byte header (big-endian), then the body."""
    ts = int(stamp_s) << 32 | int((stamp_s % 1) * (1 << 32))
    head = struct.pack(">H12s20sQQ", version, msg_type.encode(), device.encode(), ts,
                       len(body) if body_bytes is None else body_bytes)
    return head + struct.pack(">Q", crc64_ecma(body) if crc is None else crc) + body


NEWTON = 0x0B << 54 | 1 << 50  # igtl_unit: prefix (4 bits), then unit (6) and exponent (4)
MILLI = 0xB << 60
PASCAL = 0x0C << 54 | 1 << 50


def sensor(values, unit=NEWTON):
    return struct.pack(">BBQ", len(values), 0, unit) + b"".join(struct.pack(">d", v) for v in values)


def transform(x_mm, y_mm, z_mm):
    return struct.pack(">12f", 1, 0, 0, 0, 1, 0, 0, 0, 1, x_mm, y_mm, z_mm)


def track_element(name, pos, tdata=False):
    head = struct.pack(">20sBB", name.encode(), 1, 0)
    if tdata:
        return head + struct.pack(">12f", 1, 0, 0, 0, 1, 0, 0, 0, 1, *pos)
    return head + struct.pack(">7f", *pos, 0, 0, 0, 1)


def ndarray(scalar_type, rows, cols, fmt, cells):
    return struct.pack(">BBHH", scalar_type, 2, rows, cols) + b"".join(struct.pack(">" + fmt, c) for c in cells)


def igtl_seeds():
    force, pose, tactile = "ContactForce", "InstrumentTip", "TactileArray"
    tr = transform(1.0, -2.0, -0.5)
    seeds = {
        "sensor_1": igtl("SENSOR", force, sensor([2.5])),
        "sensor_3_mN": igtl("SENSOR", force, sensor([10.0, -20.0, 1500.0], NEWTON | MILLI)),
        "sensor_6": igtl("SENSOR", force, sensor([0.1, 0.2, 3.0, 0.0, 0.0, 0.01])),
        "transform": igtl("TRANSFORM", pose, tr),
        "position": igtl("POSITION", pose, struct.pack(">7f", 1.0, 2.0, -1.0, 0, 0, 0, 1)),
        "qtdata": igtl("QTDATA", pose, track_element("Tip", (1, 2, -1)) + track_element("Base", (0, 0, 9))),
        "tdata": igtl("TDATA", pose, track_element("Tip", (1, 2, -1), tdata=True)),
        "ndarray_f32": igtl("NDARRAY", tactile, ndarray(10, 3, 4, "f", [0, 10, 20, 0, 5, 500, 700, 0, 0, 0, -3, 0])),
        "ndarray_u16": igtl("NDARRAY", tactile, ndarray(5, 2, 2, "H", [1, 2, 3, 4])),
        # Protocol 3 (header version 2): 12-byte extended header, the content, 1 metadata entry.
        "v2_transform": igtl("TRANSFORM", pose, struct.pack(">HHII", 12, 10, 7, 0) + tr +
                             struct.pack(">HHHI", 1, 3, 0, 4) + b"key" + b"val!", version=2),
        "bad_crc": igtl("TRANSFORM", pose, tr, crc=0x0123456789ABCDEF),
        "truncated": igtl("TRANSFORM", pose, tr)[:80],
        "oversized": igtl("TRANSFORM", pose, tr, body_bytes=1 << 20),
        "wrong_type": igtl("STATUS", pose, struct.pack(">HQ20s", 1, 0, b"OK") + b"fine\0"),
        "bad_version": igtl("TRANSFORM", pose, tr, version=3),
        "sensor_pascal": igtl("SENSOR", force, sensor([2.5], PASCAL)),
        "sensor_nan": igtl("SENSOR", force, sensor([float("nan")])),
        "ndarray_too_big": igtl("NDARRAY", tactile, ndarray(3, 65, 65, "B", [])),
        "stream": igtl("TRANSFORM", pose, tr) + igtl("SENSOR", force, sensor([1.0]), stamp_s=1.6) +
                  igtl("NDARRAY", tactile, ndarray(3, 2, 2, "B", [0, 9, 9, 0]), stamp_s=1.7),
    }
    for name, data in seeds.items():
        write("igtl", name, data)


def udp(seq=1, stamp_ns=1_000_000, values=(0.5, 0.002, 0.01, -0.01, 0.003), magic=b"MRSS", version=1, crc=None):
    d = magic + struct.pack("<HHII", version, 0, seq, 0) + struct.pack("<q5d", stamp_ns, *values)
    return d + struct.pack("<I", zlib_crc32c(d) if crc is None else crc)


def zlib_crc32c(data):
    crc = 0xFFFFFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1
    return crc ^ 0xFFFFFFFF


def udp_seeds():
    good = udp()
    write("udp", "valid", good)
    write("udp", "bad_crc", udp(crc=0xDEADBEEF))
    write("udp", "bad_magic", udp(magic=b"MRSX"))
    write("udp", "version2", udp(version=2))
    write("udp", "short", good[:67])
    write("udp", "long", good + b"\0")
    write("udp", "nan_force", udp(values=(float("nan"), 0, 0, 0, 0.003)))
    write("udp", "out_of_range", udp(values=(25.0, 0, 0, 0, 0.003)))
    write("udp", "negative_stamp", udp(stamp_ns=-1))


if __name__ == "__main__":
    main()
