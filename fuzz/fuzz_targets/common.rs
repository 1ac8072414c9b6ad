//! Shared by the targets: cut the input into chunks as a serial port or socket would deliver it.

/// The first byte chooses the chunk sizes (1..=256, varying chunk to chunk); the rest is the stream.
/// An empty input gives an empty stream.
pub fn chunks(data: &[u8]) -> (Vec<&[u8]>, &[u8]) {
    let Some((&k, stream)) = data.split_first() else {
        return (Vec::new(), data);
    };
    let mut out = Vec::new();
    let mut rest = stream;
    let mut i = 0usize;
    while !rest.is_empty() {
        let n = 1 + (usize::from(k).wrapping_mul(i + 7) ^ i) % 256;
        let (a, b) = rest.split_at(n.min(rest.len()));
        out.push(a);
        rest = b;
        i += 1;
    }
    (out, stream)
}
