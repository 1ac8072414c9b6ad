#!/usr/bin/env python3
"""Seed corpora for the fuzz targets from the repo's own data (scripts/fuzz runs this).

Writes fuzz/corpus/<target>/seed-* (overwriting only seed-* files): a synthetic DataFlash log and
ULog file, the heads of ../shared/data/flightlogs when present, pieces of fixtures/tumble.tlog, raw MAVLink frames (including IMU messages the fixture lacks), CSV
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


def df_fmt(type_id, name, fmt, cols):
    sizes = {"b": 1, "B": 1, "M": 1, "h": 2, "H": 2, "c": 2, "C": 2, "i": 4, "I": 4, "f": 4, "e": 4,
             "E": 4, "L": 4, "q": 8, "Q": 8, "d": 8, "n": 4, "N": 16, "Z": 64, "a": 64}
    length = 3 + sum(sizes[c] for c in fmt)
    pad = lambda t, n: t.encode().ljust(n, b"\0")
    return bytes([0xA3, 0x95, 0x80, type_id, length]) + pad(name, 4) + pad(fmt, 16) + pad(cols, 64)


def dataflash_seed():
    """A DataFlash log: FMT, PARM (COMPASS_OFS), IMU, MAG with offsets, instanced MAG (FMTU `#`)."""
    out = df_fmt(0x80, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
    out += df_fmt(129, "PARM", "QNf", "TimeUS,Name,Value")
    out += df_fmt(130, "IMU", "QffffffIIfBBHH", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz")
    out += df_fmt(131, "MAG", "QhhhhhhhhhBI", "TimeUS,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S")
    out += df_fmt(132, "ATT", "QccccCCCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw")
    out += df_fmt(133, "FMTU", "QBNN", "TimeUS,FmtType,UnitIds,MultIds")
    out += df_fmt(134, "MAGI", "QBhhh", "TimeUS,I,MagX,MagY,MagZ")
    for i, (n, v) in enumerate([("COMPASS_OFS_X", -58.5), ("COMPASS_OFS_Y", 57.1), ("COMPASS_OFS_Z", 90.3),
                                ("COMPASS_DIA_X", 1.02), ("COMPASS_ODI_X", -0.01)]):
        out += bytes([0xA3, 0x95, 129]) + struct.pack("<Q", i) + n.encode().ljust(16, b"\0") + struct.pack("<f", v)
    out += bytes([0xA3, 0x95, 133]) + struct.pack("<QB", 0, 134) + b"s#GGG".ljust(16, b"\0") + b"F-CCC".ljust(16, b"\0")
    for k in range(20):
        t = 1_000_000 + k * 20_000
        out += bytes([0xA3, 0x95, 130]) + struct.pack("<Q6fIIfBBHH", t, 0.01, 0.02, -0.01, 0.3, -0.2, -9.8, 0, 0, 40.0, 1, 1, 1000, 1000)
        if k % 4 == 0:
            out += bytes([0xA3, 0x95, 131]) + struct.pack("<Q9hBI", t + 5, 219, 179, -517, -58, 57, 90, 0, 0, 0, 1, t)
            out += bytes([0xA3, 0x95, 134]) + struct.pack("<QB3h", t + 6, k % 3, 100, 200, 300)
            out += bytes([0xA3, 0x95, 132]) + struct.pack("<Q4h4H", t + 7, 0, -718, 0, 258, 0, 33710, 0, 0)
    return out


def ulog_msg(ty, body):
    return struct.pack("<HB", len(body), ord(ty)) + body


def ulog_seed():
    """A ULog file: flag bits, nested format with padding, parameters, two sensor_mag instances,
    sensor_combined, a dropout, a sync marker."""
    out = b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0)
    out += ulog_msg("B", bytes(40))
    out += ulog_msg("F", b"vec3:float x;float y;float z;")
    out += ulog_msg("F", b"sensor_mag:uint64_t timestamp;uint32_t device_id;vec3 v;float x;float y;float z;uint8_t[4] _padding0;")
    out += ulog_msg("F", b"sensor_combined:uint64_t timestamp;float[3] gyro_rad;float[3] accelerometer_m_s2;float[3] magnetometer_ga;")
    for n, v in [("CAL_MAG0_ID", None), ("CAL_MAG0_XOFF", 0.1), ("CAL_MAG0_YOFF", -0.2), ("CAL_MAG0_ZOFF", 0.05),
                 ("CAL_MAG_PRIME", None)]:
        key = (f"int32_t {n}" if v is None else f"float {n}").encode()
        val = struct.pack("<i", 1234) if v is None else struct.pack("<f", v)
        out += ulog_msg("P", bytes([len(key)]) + key + val)
    out += ulog_msg("A", struct.pack("<BH", 0, 1) + b"sensor_mag")
    out += ulog_msg("A", struct.pack("<BH", 1, 2) + b"sensor_mag")
    out += ulog_msg("A", struct.pack("<BH", 0, 3) + b"sensor_combined")
    for k in range(20):
        t = 1_000_000 + k * 10_000
        out += ulog_msg("D", struct.pack("<HQI6f", 3, t, 0, 0, 0, 0, 0.1, -0.2, -9.8)[:2 + 8] + struct.pack("<9f", 0.01, 0.0, 0.0, 0.1, -0.2, -9.8, 0.2, 0.1, -0.4))
        if k % 5 == 0:
            out += ulog_msg("D", struct.pack("<HQI6f", 1 + k % 2, t, 1234, 0.2, 0.1, -0.4, 0.2, 0.1, -0.4) + bytes(4))
        if k == 10:
            out += ulog_msg("O", struct.pack("<H", 40))
            out += ulog_msg("S", bytes([0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12]))
    return out


def main():
    write("dataflash", "synthetic", dataflash_seed())
    write("ulog", "synthetic", ulog_seed())
    # Pieces of the shared flight logs, when they are beside the checkout.
    logs = ROOT.parent / "shared" / "data" / "flightlogs"
    for name, target in [("ardupilot_plane_pixracer.bin", "dataflash"), ("px4_cubeorange_two_mags.ulg", "ulog"),
                         ("px4_auav_x21.ulg", "ulog")]:
        p = logs / name
        if p.is_file():
            b = p.read_bytes()
            write(target, f"{p.stem}-head", b[:16384])
            if target == "dataflash":
                write(target, f"{p.stem}-tail", b[-8192:])
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
