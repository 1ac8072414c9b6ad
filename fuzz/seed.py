#!/usr/bin/env python3
"""Seed corpora for the fuzz targets from the repo's own data (scripts/fuzz runs this).

Writes fuzz/corpus/<target>/seed-* (overwriting only seed-* files): pieces of
fixtures/tumble.tlog, raw MAVLink frames (including IMU messages the fixture lacks), CSV
snippets, MotionCal and CSV serial lines, and config/*.toml. Standard library only.
"""
import gzip
import pathlib
import struct

ROOT = pathlib.Path(__file__).resolve().parent.parent
CORPUS = ROOT / "fuzz" / "corpus"
CRC_EXTRA = {0: 50, 26: 170, 27: 144, 74: 20, 105: 93, 116: 76, 129: 46}


def x25(data, crc=0xFFFF):
    for b in data:
        t = (b ^ (crc & 0xFF)) & 0xFF
        t = (t ^ (t << 4)) & 0xFF
        crc = ((crc >> 8) ^ (t << 8) ^ (t << 3) ^ (t >> 4)) & 0xFFFF
    return crc


def frame(msgid, payload, v2=True, seq=0, sysid=1, compid=1):
    if v2:
        hdr = bytes([len(payload), 0, 0, seq & 0xFF, sysid, compid]) + msgid.to_bytes(3, "little")
        magic = 0xFD
    else:
        hdr = bytes([len(payload), seq & 0xFF, sysid, compid, msgid])
        magic = 0xFE
    crc = x25(bytes([CRC_EXTRA[msgid]]), x25(hdr + payload))
    return bytes([magic]) + hdr + payload + struct.pack("<H", crc)


def imu_frames():
    """RAW_IMU, SCALED_IMU, SCALED_IMU2/3 (v1 and v2), VFR_HUD and a signed frame."""
    out = []
    counts = (100, -200, 8192, 5, -7, 9, 300, -150, 420)
    for i in range(6):
        t = 1000 + i * 10
        raw = struct.pack("<Q9h", t * 1000, *counts) + struct.pack("<Bh", 0, 2500)
        scaled = struct.pack("<I9h", t, *counts) + struct.pack("<h", 3000)
        out.append(frame(27, raw, v2=i % 2 == 0, seq=i))
        out.append(frame(26, scaled, seq=i))
        out.append(frame(116, scaled, v2=False, seq=i))
        out.append(frame(129, scaled, seq=i))
        out.append(frame(74, struct.pack("<ffffhH", 1.0, 2.0, 3.0, 4.0, 90, 55), seq=i))
    signed = bytearray(frame(27, struct.pack("<Q9h", 5, *counts)))
    signed[2] |= 0x01  # incompat flag: signed (signature not checked by the decoder)
    crc = x25(bytes([CRC_EXTRA[27]]), x25(bytes(signed[1:-2])))
    signed[-2:] = struct.pack("<H", crc)
    out.append(bytes(signed) + bytes(range(13)))
    return out


def tlog_records(b):
    pos, recs = 0, []
    while pos + 10 <= len(b):
        magic, ln = b[pos + 8], b[pos + 9]
        if magic == 0xFE:
            n = 8 + ln
        elif magic == 0xFD:
            n = 12 + ln + (13 if b[pos + 10] & 1 else 0)
        else:
            break
        recs.append(b[pos:pos + 8 + n])
        pos += 8 + n
    return recs


def write(target, name, data):
    d = CORPUS / target
    d.mkdir(parents=True, exist_ok=True)
    (d / f"seed-{name}").write_bytes(data if isinstance(data, bytes) else data.encode())


def main():
    tlog = (ROOT / "fixtures" / "tumble.tlog").read_bytes()
    recs = tlog_records(tlog)
    # tlog: record-aligned pieces of ~3 KB from across the file, unaligned cuts, gzip.
    for k, start in enumerate(range(0, len(recs), len(recs) // 6)):
        piece = b"".join(recs[start:start + 60])
        write("tlog", f"piece{k}", piece)
    write("tlog", "unaligned", tlog[1001:1001 + 3000])
    write("tlog", "gz", gzip.compress(b"".join(recs[:60])))
    write("tlog", "gz-truncated", gzip.compress(b"".join(recs[:60]))[:700])
    ts0 = struct.unpack(">Q", recs[0][:8])[0]
    synth = b"".join(struct.pack(">Q", ts0 + i * 5000) + f for i, f in enumerate(imu_frames()))
    write("tlog", "imu-kinds", synth)
    write("tlog", "csv", "t,ax,ay,az,mx,my,mz\n0,0,0,-9.8,20,0,40\n0.01,0,0,-9.8,21,0,40\n")

    # mavlink_frames: first byte picks the chunking, the rest is a frame stream.
    frames = [r[8:] for r in recs]
    for k, start in enumerate((0, len(frames) // 2, len(frames) - 40)):
        write("mavlink_frames", f"stream{k}", bytes([k * 37 + 1]) + b"".join(frames[start:start + 40]))
    write("mavlink_frames", "imu-kinds", b"\x05" + b"".join(imu_frames()))
    write("mavlink_frames", "garbage", b"\x03" + b"\x00\x13\xfd\x77" + imu_frames()[0] + b"\x01\x02\x03")

    # csv: header variants, user column names, empty cells, NaN/inf, comments, quotes.
    write("csv", "default", "t,ax,ay,az,gx,gy,gz,mx,my,mz,temp\n"
          "0.00,0.1,0.0,-9.8,0.01,0.0,0.0,20.1,1.0,40.2,25\n"
          "0.01,0.1,0.0,-9.8,0.01,0.0,0.0,20.3,1.1,40.0,25\n")
    write("csv", "subset", "# comment\n\nmz,t,mx,my,ax,ay,az\n3,0.0,1,2,,,\n6,0.1,4,5,0,0,-9.8\nbad,row\n9,0.2,7,8,0,NaN,1\n")
    write("csv", "mapped", "\"time_ms\",AccX,AccY,AccZ,MagX,MagY,MagZ\n10,0,0,-1,200,10,400\n20,0,0,-1,201,11,401\n")
    write("csv", "full", "t,ax,ay,az,gx,gy,gz,mx,my,mz,temp,throttle,current,ref_qw,ref_qx,ref_qy,ref_qz,moving\n"
          "1,0,0,9.8,0,0,0,10,20,30,21,0.5,3.2,1,0,0,0,1\n1.1,inf,0,9.8,,,,10,20,30,,,,,,,,0\n")

    # serial_lines: first byte picks the chunking; MotionCal and CSV lines, CRLF, noise.
    write("serial_lines", "motioncal", b"\x07" + b"Raw:8192,-4096,0,16,-32,160,100,-25,0\r\n"
          b"Uni:0.1,0.2\r\nCal1:1,2,3\r\n Raw: 1, 2,3,4,5,6,7,8,9\r\nRaw:1,2,3\n")
    write("serial_lines", "csv", b"\x0b" + b"0.1,0.0,-1.0,0.01,0.02,0.03,20.0,1.5,40.0\n"
          b"1500,0,0,-1,99,10,20,30\n1600,,,,0,10,20,30\nt,ax,ay,az,_,mx,my,mz\n1,2,3\n")

    # config: the shipped configs and a place.
    for p in sorted((ROOT / "config").glob("*.toml")):
        write("config", p.stem, p.read_bytes())
    write("config", "place", "[place]\nlatitude_deg = 45.0\nlongitude_deg = 7.0\naltitude_m = 300\n"
          "date = \"2026-03-01\"\n[orientation]\nsensor = \"ROTATION_ROLL_180_YAW_45\"\n"
          "[accept.mag]\nmax_rms_ratio = 0.1\n[input.csv.columns]\nax = \"AccX\"\n[input.csv.scales]\nax = 9.80665\n")


if __name__ == "__main__":
    main()
