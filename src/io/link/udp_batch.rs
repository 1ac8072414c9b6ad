//! Many UDP datagrams per system call: `recvmmsg(2)` on Linux, one `recv_from` per datagram
//! elsewhere. At 1 kHz a read every 20 ms (the default poll) takes about twenty datagrams in one
//! call instead of twenty-one (the last one finding nothing).

use std::io;
use std::net::{SocketAddr, UdpSocket};

/// Datagrams taken per call at most.
pub(crate) const BATCH: usize = 32;
/// Room for each datagram: the largest a UDP datagram can be, so none is ever cut short. The
/// buffers are allocated zeroed, so only the pages the kernel writes to become resident.
const DATAGRAM_MAX: usize = 65_536;

/// Buffers for one batch, and what the last read put in them.
pub(crate) struct UdpBatch {
    bufs: Vec<Vec<u8>>,
    lens: [usize; BATCH],
    from: [Option<SocketAddr>; BATCH],
}

impl UdpBatch {
    pub fn new() -> UdpBatch {
        UdpBatch {
            bufs: (0..BATCH).map(|_| vec![0u8; DATAGRAM_MAX]).collect(),
            lens: [0; BATCH],
            from: [None; BATCH],
        }
    }

    /// Datagram `i` of the last read and its sender (`None` for an address family this does not
    /// know, which cannot happen on an IPv4 or IPv6 socket).
    pub fn get(&self, i: usize) -> (&[u8], Option<SocketAddr>) {
        (&self.bufs[i][..self.lens[i]], self.from[i])
    }

    /// Take up to [`BATCH`] queued datagrams without waiting; `Ok(0)` when none is queued.
    #[cfg(target_os = "linux")]
    pub fn recv(&mut self, sock: &UdpSocket) -> io::Result<usize> {
        use std::os::fd::AsRawFd;
        // SAFETY: all-zero iovec, sockaddr_storage and mmsghdr values are valid (null pointers,
        // zero lengths); every pointer is set below before the kernel sees it.
        let mut iov: [libc::iovec; BATCH] = unsafe { std::mem::zeroed() };
        let mut names: [libc::sockaddr_storage; BATCH] = unsafe { std::mem::zeroed() };
        let mut hdrs: [libc::mmsghdr; BATCH] = unsafe { std::mem::zeroed() };
        for i in 0..BATCH {
            iov[i].iov_base = self.bufs[i].as_mut_ptr().cast();
            iov[i].iov_len = self.bufs[i].len();
            hdrs[i].msg_hdr.msg_iov = &mut iov[i];
            hdrs[i].msg_hdr.msg_iovlen = 1;
            hdrs[i].msg_hdr.msg_name = (&mut names[i] as *mut libc::sockaddr_storage).cast();
            hdrs[i].msg_hdr.msg_namelen =
                std::mem::size_of::<libc::sockaddr_storage>() as libc::socklen_t;
        }
        // SAFETY: each header points at a live buffer of the stated length and at a
        // sockaddr_storage of the stated size; the kernel writes within them only, and they outlive
        // the call.
        let n = unsafe {
            libc::recvmmsg(
                sock.as_raw_fd(),
                hdrs.as_mut_ptr(),
                BATCH as libc::c_uint,
                libc::MSG_DONTWAIT,
                std::ptr::null_mut(),
            )
        };
        if n < 0 {
            let e = io::Error::last_os_error();
            return if e.kind() == io::ErrorKind::WouldBlock {
                Ok(0)
            } else {
                Err(e)
            };
        }
        let n = n as usize;
        for i in 0..n {
            self.lens[i] = (hdrs[i].msg_len as usize).min(DATAGRAM_MAX);
            self.from[i] = socket_addr(&names[i], hdrs[i].msg_hdr.msg_namelen);
        }
        Ok(n)
    }

    /// Take up to [`BATCH`] queued datagrams without waiting; `Ok(0)` when none is queued.
    #[cfg(not(target_os = "linux"))]
    pub fn recv(&mut self, sock: &UdpSocket) -> io::Result<usize> {
        for i in 0..BATCH {
            match sock.recv_from(&mut self.bufs[i]) {
                Ok((len, from)) => {
                    self.lens[i] = len;
                    self.from[i] = Some(from);
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(i),
                Err(e) if i > 0 => {
                    // Hand on what was read; the error comes back on the next call.
                    let _ = e;
                    return Ok(i);
                }
                Err(e) => return Err(e),
            }
        }
        Ok(BATCH)
    }
}

/// Ask for a receive buffer of `bytes` (SO_RCVBUF; the kernel caps it at `net.core.rmem_max`),
/// so datagrams can wait longer between reads. Only ever grows the buffer. Returns its size as
/// SO_RCVBUF reads back (what the kernel counts queued datagrams against: twice what was set).
#[cfg(target_os = "linux")]
pub(crate) fn grow_receive_buffer(sock: &UdpSocket, bytes: usize) -> io::Result<usize> {
    use std::os::fd::AsRawFd;
    let fd = sock.as_raw_fd();
    let read = || {
        let mut cur: libc::c_int = 0;
        let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
        // SAFETY: `cur` and `len` are live and sized for an int option.
        let r = unsafe {
            libc::getsockopt(
                fd,
                libc::SOL_SOCKET,
                libc::SO_RCVBUF,
                (&mut cur as *mut libc::c_int).cast(),
                &mut len,
            )
        };
        if r != 0 {
            return Err(io::Error::last_os_error());
        }
        Ok(usize::try_from(cur).unwrap_or(0))
    };
    let cur = read()?;
    if cur >= bytes {
        return Ok(cur);
    }
    let want = libc::c_int::try_from(bytes).unwrap_or(libc::c_int::MAX);
    // SAFETY: `want` is a live int of the stated size.
    let r = unsafe {
        libc::setsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_RCVBUF,
            (&want as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    if r != 0 {
        return Err(io::Error::last_os_error());
    }
    read()
}

/// Elsewhere the buffer is left as the system made it, of a size not known (0).
#[cfg(not(target_os = "linux"))]
pub(crate) fn grow_receive_buffer(_sock: &UdpSocket, _bytes: usize) -> io::Result<usize> {
    Ok(0)
}

/// The sender's address from what `recvmmsg` wrote.
#[cfg(target_os = "linux")]
fn socket_addr(s: &libc::sockaddr_storage, len: libc::socklen_t) -> Option<SocketAddr> {
    use std::net::{Ipv4Addr, Ipv6Addr, SocketAddrV6};
    let len = len as usize;
    match s.ss_family as libc::c_int {
        libc::AF_INET if len >= std::mem::size_of::<libc::sockaddr_in>() => {
            // SAFETY: the family says the storage holds a sockaddr_in, which it is large and
            // aligned enough for.
            let a = unsafe { &*(s as *const libc::sockaddr_storage).cast::<libc::sockaddr_in>() };
            Some(SocketAddr::from((
                Ipv4Addr::from(u32::from_be(a.sin_addr.s_addr)),
                u16::from_be(a.sin_port),
            )))
        }
        libc::AF_INET6 if len >= std::mem::size_of::<libc::sockaddr_in6>() => {
            // SAFETY: as above, for sockaddr_in6.
            let a = unsafe { &*(s as *const libc::sockaddr_storage).cast::<libc::sockaddr_in6>() };
            Some(SocketAddr::V6(SocketAddrV6::new(
                Ipv6Addr::from(a.sin6_addr.s6_addr),
                u16::from_be(a.sin6_port),
                a.sin6_flowinfo,
                a.sin6_scope_id,
            )))
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn takes_queued_datagrams_in_batches_with_their_senders() {
        let rx = UdpSocket::bind("127.0.0.1:0").unwrap();
        rx.set_nonblocking(true).unwrap();
        let tx = UdpSocket::bind("127.0.0.1:0").unwrap();
        let mut b = UdpBatch::new();
        assert_eq!(b.recv(&rx).unwrap(), 0, "nothing queued yet");
        let sizes: Vec<usize> = (0..BATCH + 5).map(|i| 1 + i * 97).chain([9000]).collect();
        for (i, &n) in sizes.iter().enumerate() {
            let d: Vec<u8> = (0..n).map(|k| (k + i) as u8).collect();
            tx.send_to(&d, rx.local_addr().unwrap()).unwrap();
        }
        let mut got = vec![];
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while got.len() < sizes.len() && std::time::Instant::now() < deadline {
            let n = b.recv(&rx).unwrap();
            assert!(n <= BATCH);
            for i in 0..n {
                let (bytes, from) = b.get(i);
                assert_eq!(from, Some(tx.local_addr().unwrap()));
                got.push(bytes.to_vec());
            }
        }
        assert_eq!(got.len(), sizes.len());
        for (i, (d, &n)) in got.iter().zip(&sizes).enumerate() {
            assert_eq!(d.len(), n);
            assert!(d.iter().enumerate().all(|(k, &v)| v == (k + i) as u8));
        }
    }
}
