#!/usr/bin/env python3
"""What of a training run's logs must not depend on timing or on where the run was killed.

  run_logs.py metrics RUN/metrics.jsonl   every line, the wall-clock fields (elapsed_s,
                                          data_wait_s, gradient_sum_wait_s) removed
  run_logs.py events RUN/events.out...    every scalar as "tag step value" (tf.Event records,
                                          CRCs checked; the wait times left out)
A record cut short, a CRC mismatch or a metrics line that is not JSON fails (exit 1).
"""
import json
import re
import struct
import sys


def metrics(path):
    for number, line in enumerate(open(path, encoding="utf-8"), 1):
        try:
            json.loads(line)
        except ValueError as e:
            sys.exit(f"{path}:{number}: not JSON ({e})")
        print(re.sub(r', "(elapsed_s|data_wait_s|gradient_sum_wait_s)": [0-9.eE+-]+', "", line.rstrip("\n")))


def crc32c(data):
    crc = 0xFFFFFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def masked_crc32c(data):
    c = crc32c(data)
    return (((c >> 15) | (c << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def fields(buf):
    """(field number, wire type, value) of a protocol buffer message."""
    at = 0
    while at < len(buf):
        key, at = varint(buf, at)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, at = varint(buf, at)
        elif wire == 1:
            value, at = buf[at:at + 8], at + 8
        elif wire == 5:
            value, at = buf[at:at + 4], at + 4
        elif wire == 2:
            n, at = varint(buf, at)
            value, at = buf[at:at + n], at + n
        else:
            raise ValueError(f"wire type {wire}")
        yield number, wire, value


def varint(buf, at):
    value = shift = 0
    while True:
        b = buf[at]
        at += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, at


def events(path):
    data = open(path, "rb").read()
    at = 0
    while at < len(data):
        if at + 12 > len(data):
            sys.exit(f"{path}: a record cut short at byte {at}")
        (length,) = struct.unpack_from("<Q", data, at)
        (length_crc,) = struct.unpack_from("<I", data, at + 8)
        event = data[at + 12:at + 12 + length]
        if length_crc != masked_crc32c(data[at:at + 8]) or len(event) != length or at + 16 + length > len(data):
            sys.exit(f"{path}: a record cut short or corrupt at byte {at}")
        (event_crc,) = struct.unpack_from("<I", data, at + 12 + length)
        if event_crc != masked_crc32c(event):
            sys.exit(f"{path}: CRC mismatch at byte {at}")
        at += 16 + length
        step = 0
        for number, _, value in fields(event):
            if number == 2:
                step = value
        for number, _, summary in fields(event):
            if number != 5:
                continue
            for _, _, v in fields(summary):
                tag, scalar = "", None
                for n, _, x in fields(v):
                    if n == 1:
                        tag = x.decode()
                    elif n == 2:
                        (scalar,) = struct.unpack("<f", x)
                if tag not in ("train/data_wait_s", "train/gradient_sum_wait_s"):
                    print(f"{tag} {step} {scalar!r}")


if __name__ == "__main__":
    {"metrics": metrics, "events": events}[sys.argv[1]](sys.argv[2])
