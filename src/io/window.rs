//! A window over a byte stream: the readers of logs read as streams (`.tlog`, DataFlash, ULog) keep
//! a bounded window of the file and move it on as they go.

/// Bytes read from a stream at a time into a decoder's window ([`crate::io::decode::TlogStream`], the DataFlash
/// and ULog readers): large enough that a read costs little per record, small against a log.
pub(crate) const STREAM_CHUNK_BYTES: usize = 256 * 1024;

/// Drop the bytes of `buf` before `pos` (moving `base` on by as many) and read up to
/// [`STREAM_CHUNK_BYTES`] more; the end of the stream or a read error sets `eof` (a truncated
/// gzip member ends the stream as its end would; other errors are kept in `error`).
pub(crate) fn fill_window(
    reader: &mut impl std::io::Read,
    buf: &mut Vec<u8>,
    (pos, base): (&mut usize, &mut usize),
    eof: &mut bool,
    error: &mut Option<std::io::Error>,
) {
    buf.drain(..*pos);
    *base += *pos;
    *pos = 0;
    let want = buf.len() + STREAM_CHUNK_BYTES;
    while buf.len() < want {
        let have = buf.len();
        buf.resize(want, 0);
        match reader.read(&mut buf[have..]) {
            Ok(0) => {
                buf.truncate(have);
                *eof = true;
                return;
            }
            Ok(k) => buf.truncate(have + k),
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => buf.truncate(have),
            Err(e) => {
                buf.truncate(have);
                *eof = true;
                if e.kind() != std::io::ErrorKind::UnexpectedEof {
                    *error = Some(e);
                }
                return;
            }
        }
    }
}
