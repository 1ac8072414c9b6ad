//! A window over a byte stream: the readers of logs read as streams (`.tlog`, DataFlash, ULog) keep
//! a bounded window of the file and move it on as they go.

/// Bytes read from a stream at a time into a decoder's window ([`crate::io::decode::TlogStream`], the DataFlash
/// and ULog readers): large enough that a read costs little per record, small against a log.
pub(crate) const STREAM_CHUNK_BYTES: usize = 256 * 1024;

/// The bytes of a stream held by a reader: a buffer allocated (and zeroed) once and then reused,
/// so moving the window on costs a copy of the bytes still to be read and the reads, not a fresh
/// zeroing of a chunk per read.
#[derive(Debug, Default)]
pub(crate) struct StreamBuf {
    /// The buffer; its first `filled` bytes are the window.
    bytes: Vec<u8>,
    filled: usize,
}

impl StreamBuf {
    /// An empty window with room for `capacity` bytes before it grows.
    pub fn with_capacity(capacity: usize) -> StreamBuf {
        StreamBuf {
            bytes: Vec::with_capacity(capacity),
            filled: 0,
        }
    }

    /// The bytes in the window.
    #[inline]
    pub fn data(&self) -> &[u8] {
        &self.bytes[..self.filled]
    }

    /// Drop the bytes before `pos` (moving `base` on by as many) and read up to
    /// [`STREAM_CHUNK_BYTES`] more; the end of the stream or a read error sets `eof` (a truncated
    /// gzip member ends the stream as its end would; other errors are kept in `error`).
    pub fn fill(
        &mut self,
        reader: &mut impl std::io::Read,
        (pos, base): (&mut usize, &mut usize),
        eof: &mut bool,
        error: &mut Option<std::io::Error>,
    ) {
        self.bytes.copy_within(*pos..self.filled, 0);
        self.filled -= *pos;
        *base += *pos;
        *pos = 0;
        let want = self.filled + STREAM_CHUNK_BYTES;
        if self.bytes.len() < want {
            // Zeroed once, when the window first needs the room.
            self.bytes.resize(want, 0);
        }
        while self.filled < want {
            match reader.read(&mut self.bytes[self.filled..want]) {
                Ok(0) => {
                    *eof = true;
                    return;
                }
                Ok(k) => self.filled += k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => {
                    *eof = true;
                    if e.kind() != std::io::ErrorKind::UnexpectedEof {
                        *error = Some(e);
                    }
                    return;
                }
            }
        }
    }
}

/// The bytes a log reader reads: a whole file's bytes, or a stream read through a bounded
/// window that [`Window::refill`] moves on (the DataFlash and ULog readers).
pub(crate) struct Window<'a> {
    /// Whole bytes (empty for a stream).
    data: &'a [u8],
    stream: Option<Stream<'a>>,
}

/// A stream a [`Window`] reads, and where its buffer stands in it.
struct Stream<'a> {
    reader: Box<dyn std::io::Read + 'a>,
    buf: StreamBuf,
    /// Offset of `buf` in the stream.
    base: usize,
    eof: bool,
    error: Option<std::io::Error>,
}

impl<'a> Window<'a> {
    /// A window that is all of `data`.
    pub fn whole(data: &'a [u8]) -> Self {
        Window { data, stream: None }
    }

    /// A window over the stream `reader` gives, empty until the first [`Window::refill`].
    pub fn stream(reader: impl std::io::Read + 'a) -> Self {
        Window {
            data: &[],
            stream: Some(Stream {
                reader: Box::new(reader),
                buf: StreamBuf::default(),
                base: 0,
                eof: false,
                error: None,
            }),
        }
    }

    /// The bytes in the window.
    pub fn bytes(&self) -> &[u8] {
        match &self.stream {
            Some(s) => s.buf.data(),
            None => self.data,
        }
    }

    /// Read more of a stream when fewer than `need` bytes are left after `pos` (an offset in the
    /// window, moved with it as the bytes before it are dropped).
    pub fn refill(&mut self, pos: &mut usize, need: usize) {
        let Some(s) = self.stream.as_mut() else {
            return;
        };
        if s.eof || s.buf.data().len() - *pos >= need {
            return;
        }
        s.buf
            .fill(&mut s.reader, (pos, &mut s.base), &mut s.eof, &mut s.error);
    }

    /// The offset in the input of `pos`, an offset in the window.
    pub fn offset(&self, pos: usize) -> usize {
        pos + self.stream.as_ref().map_or(0, |s| s.base)
    }

    /// The whole input is in the window (whole bytes, or a stream read to its end).
    pub fn at_end(&self) -> bool {
        self.stream.as_ref().is_none_or(|s| s.eof)
    }

    /// The input's length, once all of it is in the window.
    pub fn known_len(&self) -> Option<usize> {
        self.at_end().then(|| self.offset(self.bytes().len()))
    }

    /// The error that ended a stream early, if one did (taken).
    pub fn take_error(&mut self) -> Option<std::io::Error> {
        self.stream.as_mut().and_then(|s| s.error.take())
    }
}
