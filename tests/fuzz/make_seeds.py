#!/usr/bin/env python3
"""Writes the seed corpora of the byte-oriented fuzz targets (corpus/<target>/seed-*) from the byte
sequences of the codec tests (tests/drivers/codecs) and the README's file formats. The cal.json,
TOML and LCM seeds come from the project's own writers (see README.md in this directory)."""
import os
import struct
import zlib

HERE = os.path.dirname(os.path.abspath(__file__))


def put(target, name, data):
    d = os.path.join(HERE, "corpus", target)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, "seed-" + name), "wb") as f:
        f.write(data)


def crc16_ccitt(data, crc=0xFFFF):
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def ads_frame(response, codes):
    f = bytes([response >> 8, response & 0xFF, 0])
    for c in codes:
        f += (c & 0xFFFFFF).to_bytes(3, "big")
    crc = crc16_ccitt(f)
    return f + bytes([crc >> 8, crc & 0xFF, 0])


# ADS131M04: config (channel map 0,1,2; gains 0; stuck 3), then frames of ads131m04_test.cpp.
normal = bytes([0x01, 0x0F, 0x00, 0x12, 0x34, 0x56, 0xFF, 0xFF, 0xFE,
                0x00, 0x00, 0x01, 0x80, 0x00, 0x00, 0x39, 0x57, 0x00])
saturated = bytes([0x01, 0x0F, 0x00, 0x7F, 0xFF, 0xFF, 0x00, 0x00, 0x10,
                   0x80, 0x00, 0x00, 0x00, 0x00, 0x00, 0xDB, 0x55, 0x00])
assert ads_frame(0x010F, [0x123456, -2, 1, -0x800000]) == normal
cfg = bytes([0b100100, 0x00, 0x00, 3])
put("ads131m04", "test-frames", cfg + normal + saturated + normal)
put("ads131m04", "stuck-and-reset",
    cfg + ads_frame(0x0507, [5, 5, 5, 0]) * 4 + ads_frame(0x0100, [1, 2, 3, 4]))
put("ads131m04", "crc-error", cfg + normal[:-3] + b"\x00\x00\x00" + saturated)

# ASCII lines of serial_fluxgate_test.cpp: config '$', ',', optional checksum, 4 fields, scale 1.
ascii_cfg = bytes([0x01 | (1 << 3), 4, 0, 1, 2, 0])
put("serial_ascii", "test-lines",
    ascii_cfg + b"$MAG,12345.6,-2345.1,40000.0*56\r\n$MAG,1,2,3\nxx$MAG,1,2,3\r\n$MAG,4,5,6*50\r\n")
put("serial_ascii", "bad-lines",
    ascii_cfg + b"$MAG,1,2*00\r\n$MAG,1,2,3,4\r\n$MAG,1e999,2,3\r\n$MA$MAG,1,2,3\n" + b"9" * 120 + b"\n")
# No start character, ' ' separator, no tag, fields y z x: "-2.5 40.125 1.5e1".
put("serial_ascii", "no-start",
    bytes([0x04 | 0x20, 0, 2, 0, 1, 0]) + b"-2.5 40.125 1.5e1\r\n\r\n7 8 9\n1 2 3*00\n")

# G-882 lines of g882_test.cpp: config '$', one analog channel, no Julian clock, no signal
# threshold; then three channels + Julian clock; then a signal threshold of 520 counts.
put("g882", "manual-lines",
    bytes([0 | (1 << 3), 0]) + b"$ 48123.456,0721\r\n$100001.250,9999\n$ 17000.000,0000\r\n")
put("g882", "bad-lines",
    bytes([0 | (1 << 3), 0]) + b"noise\r\n$ 48123.45x,0721\r\n$ 12000.000,0721\r\n"
    b"$ 4812$ 48123.456,0721\r\n$ 48123.456" + b"9" * 80 + b"\r\n$ 48200.000,0800\r\n")
put("g882", "channels-julian",
    bytes([4 | (3 << 3), 13]) + b"$ 54369.127,1234,5678,0000\r\n$ 54369.127,0499,0,0\r\n"
    b"$ 48123.456,0721,5678,0000,D123H04M05S06_78\r\n$ 48123.456,0721,5678,0000,H04M05\r\n")

# HMR2300 records of the datasheet test, garbage, the lock-loss regression stream.
rec1 = bytes([0x3A, 0x98, 0xE2, 0xB4, 0x75, 0x30, 0x0D])
rec2 = bytes([0x8A, 0xD0, 0x00, 0x00, 0xC3, 0x74, 0x0D])
put("hmr2300", "datasheet", b"\x00" + rec1 + rec2 + rec1 + rec2)
put("hmr2300", "garbage-then-records", b"\x00" + b"\x0d\x01\x0d\xff" + rec1 + rec2 + b"\x0d" + rec1 + rec2)
put("hmr2300", "lock-loss-overlap", b"\x00" + bytes([
    0x00, 0x01, 0x00, 0x02, 0x00, 0x03, 0x0D, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x0D,
    0x00, 0x00, 0x0D, 0x00, 0x04, 0x00, 0x05, 0x00, 0x06, 0x0D,
    0x00, 0x07, 0x00, 0x08, 0x00, 0x09, 0x0D]))


# SBG CAN: one epoch per attitude as sbg_can_test.cpp writes it (selector indices into the
# default ids: 0 STATUS_01, 1 STATUS_03, 2 EKF_INFO, 3 EKF_QUAT, 4 EKF_EULER, 5 ORIENTATION_ACC).
def can(sel, payload):
    return bytes([sel, len(payload)]) + payload


def epoch(t_us, q, euler):
    return (can(0, struct.pack("<IHH", t_us, 0, 0)) + can(1, struct.pack("<IH", 0x14 | 4, 0)) +
            can(5, struct.pack("<HHH", 100, 100, 300)) + can(2, struct.pack("<I", t_us)) +
            can(4, struct.pack("<hhh", *euler)) + can(3, struct.pack("<hhhh", *q)))


put("sbg_can", "quaternion-epochs",
    b"\x00" + epoch(1000, (32767, 0, 0, 0), (0, 0, 0)) + epoch(11000, (23170, 0, 0, 23170), (100, -200, 15708)))
put("sbg_can", "euler-epochs", b"\x01" + epoch(5000, (32767, 0, 0, 0), (1000, -500, 31415)) +
    can(4, struct.pack("<hhh", 1, 2, 3)) + can(2, b"\x01\x02"))

# CSV recordings in the formats of csv_test.cpp.
put("csv", "li", b"# recorded by magvec simulate\nt_s,hx_nT,hy_nT,hz_nT,F_nT,alpha_deg,beta_deg,gamma_deg\n"
    b"0,1000.5,-2000,45000,49000,10,20,30\n0.001,nan,nan,nan,49000,10,20,30\n")
put("csv", "quaternion-uT", b"t_s,hx_uT,hy_uT,hz_uT,qw,qx,qy,qz,theta_deg\n0,1.5,-2,45,1,0,0,0,45\n"
    b"1,\"1.5\",2,3,0.7071067811865476,0,0,0.7071067811865476,nan\n")
put("csv", "ypr-rad-crlf", b"\xef\xbb\xbft_s,hx_nT,hy_nT,hz_nT,yaw_rad,pitch_rad,roll_rad,extra\r\n"
    b"0,1,2,3,0.1,0.2,0.3,x\r\n2,+4,-5e3,6.5E2,nan,0,0,\"a,\"\"b\"\r\n")

# ParamStore: two 256-byte slots, slot 0 holds record seq 7, slot 1 seq 8 (torn magic), then a blob.
def record(seq, payload):
    body = struct.pack("<HHII", 1, 20, seq, len(payload))
    crc = zlib.crc32(body + payload) & 0xFFFFFFFF
    return struct.pack("<I", 0x5350564D) + body + struct.pack("<I", crc) + payload


def slot(rec):
    return rec + b"\xff" * (256 - len(rec))


put("param_store", "two-slots", slot(record(7, b'{"cal_id": 3}')) + slot(record(8, b"newer")) + b"blob")
put("param_store", "torn-newer", slot(record(7, b"old")) + slot(b"\xff\xff\xff\xff" + record(8, b"x")[4:]) + b"")
put("param_store", "wrapped-sequence",
    slot(record(0xFFFFFFFF, b"a" * 40)) + slot(record(0, b"b")) + b"c" * 236)
