#!/usr/bin/env python3
"""Writes the seed corpora of tests/fuzz/corpus/ from tests/protocol/golden_vectors.txt.

    python3 tests/fuzz/make_seeds.py

Input formats are those of tests/fuzz/fuzz_entry.hpp. Rerun after the golden vectors change.
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
    for name in ["heartbeat", "valve_currents", "telemetry", "identity", "cell_targets", "config_data"]:
        write("packet", name, bytes.fromhex(v[(name, "packet")][0]))
    report = bytes.fromhex(v[("status", "packet")][0])
    write("packet", "status_hid_report", report + bytes(64 - len(report)))
    v2 = bytearray(bytes.fromhex(v[("heartbeat", "packet")][0]))
    v2[0] = 2
    write("packet", "version2_heartbeat", bytes(v2))

    for name in ["valve_currents", "valve_currents_partial", "telemetry", "cell_targets", "identity", "config_write"]:
        write("can_classic", name, bytes([NODE_BYTE]) + b"".join(classic_record(t) for t in v[(name, "can")]))
    mgmt = b"".join(classic_record(v[(n, "can")][0]) for n in ["heartbeat", "status", "time_sync", "state_request"])
    write("can_classic", "management", bytes([NODE_BYTE]) + mgmt)

    for name in ["valve_currents", "telemetry", "identity", "heartbeat", "config_ack"]:
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


if __name__ == "__main__":
    main()
