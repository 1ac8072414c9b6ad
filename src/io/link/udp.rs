//! UDP links: a datagram decoded on its own, and the socket served by waiting on each datagram or
//! by polling in batches on a fixed grid.

use super::End;
use super::*;

/// Frames of one UDP datagram. Unlike the stream decoder, a datagram's end is a frame boundary:
/// an unfinished frame there is counted `truncated`; each run of garbage counts one `resync`.
/// Each frame goes to `emit` as it is found; returns how many.
pub(super) fn decode_datagram(
    buf: &[u8],
    stats: &mut DecodeStats,
    mut emit: impl FnMut(Frame),
) -> u64 {
    let mut n_frames = 0;
    let mut pos = 0;
    let mut in_garbage = false;
    while pos < buf.len() {
        match decode::parse_frame(&buf[pos..]) {
            FrameParse::Frame(f, n) => {
                emit(f);
                n_frames += 1;
                pos += n;
                in_garbage = false;
            }
            FrameParse::Incomplete => {
                stats.skip("truncated");
                break;
            }
            FrameParse::Skip(n, why) => {
                if why != SkipReason::Resync || !in_garbage {
                    stats.skip(why.name());
                }
                // The bytes after a damaged frame's first byte are its rest, not new garbage.
                in_garbage = matches!(why, SkipReason::Resync | SkipReason::BadCrc);
                pos += n.max(1);
            }
        }
    }
    n_frames
}

pub(super) fn merge_stats(dst: &mut DecodeStats, src: &DecodeStats) {
    dst.records += src.records;
    dst.counts.add(&src.counts);
    for (k, v) in &src.skipped {
        *dst.skipped.entry(k.clone()).or_insert(0) += v;
    }
    dst.time.add(&src.time);
}

pub(super) fn transient_udp_error(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    // ICMP port-unreachable from an earlier send shows up as refused/reset: the peer is not up
    // yet, which is normal for UDP.
    matches!(
        e.kind(),
        ConnectionRefused | ConnectionReset | WouldBlock | Interrupted
    )
}

/// Serve a UDP socket: each datagram is decoded on its own; outbound goes to the target
/// (udpout) or to the last sender (udpin).
pub(super) async fn serve_udp(
    sh: &Shared,
    ctl: &mut Control,
    sock: &UdpSocket,
    target: Option<SocketAddr>,
    rx: &mut Rx,
) -> End {
    let silent_after = sh.tuning.silent;
    let mut peer: Option<SocketAddr> = None;
    let mut buf = vec![0u8; 65_536];
    let mut last = Instant::now();
    let mut silent = false;
    loop {
        let deadline = last + silent_after.unwrap_or(Duration::from_secs(3600));
        tokio::select! {
            biased;
            _ = wait_stop(&mut ctl.shutdown) => return End::Stop,
            r = sock.recv_from(&mut buf) => match r {
                Ok((n, from)) => {
                    if target.is_none() && peer != Some(from) {
                        tracing::debug!("link {}: udp peer {from}", sh.index);
                        peer = Some(from);
                    }
                    last = Instant::now();
                    silent = false;
                    if !rx.on_bytes(sh, &buf[..n], true) {
                        return End::Stop;
                    }
                }
                Err(e) if transient_udp_error(&e) => {}
                Err(e) => return End::Lost(format!("udp receive failed: {e}")),
            },
            m = ctl.outbound.recv(), if ctl.outbound_open => match m {
                None => ctl.outbound_open = false,
                Some(bytes) => {
                    let sent = match (target, peer) {
                        (Some(_), _) => sock.send(&bytes).await.map(|_| ()),
                        (None, Some(p)) => sock.send_to(&bytes, p).await.map(|_| ()),
                        (None, None) => Err(std::io::Error::other("no peer has sent anything yet")),
                    };
                    if let Err(e) = sent {
                        tracing::trace!("link {}: udp send dropped: {e}", sh.index);
                        LinkCounters::add(&sh.counters.outbound_dropped, 1);
                    }
                }
            },
            _ = tokio::time::sleep_until(deadline), if silent_after.is_some() && !silent => {
                silent = true;
                if !sh.status(LinkStatus::Silent { for_s: last.elapsed().as_secs_f64() }) {
                    return End::Stop;
                }
            }
        }
    }
}

/// Receive-buffer bytes one small datagram takes in Linux's accounting (its `truesize`: the
/// payload's allocation and the socket buffer around it), as SO_RCVBUF reads back: Linux's default
/// `rmem_default` of 212992 bytes holds 256 datagrams of a HIGHRES_IMU's size (measured on
/// loopback: 256 queued at the default, 2520 at 2 MiB).
pub(super) const DATAGRAM_TRUESIZE: usize = 832;

/// Datagrams per poll above which the poll period shrinks (aiming at half this many per read), and
/// below which it doubles back towards the configured one, for a receive buffer of `bytes` (0:
/// not known, taken as Linux's default): a fast sender is read often enough that the buffer never
/// fills between reads, 3/8 of it at most (96 of the default's 256). The grow threshold is under
/// half the shrink one, so doubling the period never overshoots it.
pub(super) fn poll_thresholds(bytes: usize) -> (usize, usize) {
    let holds = (bytes / DATAGRAM_TRUESIZE).max(256);
    let shrink_above = holds * 3 / 8;
    (shrink_above, shrink_above * 5 / 12)
}
/// Shortest poll period.
pub(super) const POLL_MIN: Duration = Duration::from_millis(1);
/// How long a shortened poll period is kept after the last busy read before it may grow again, so
/// a sender that pauses briefly does not come back to a long period (and a full buffer).
pub(super) const POLL_HOLD: Duration = Duration::from_secs(2);
/// Receive buffer asked for on a polled socket, bytes (the kernel caps it at `net.core.rmem_max`).
pub(super) const POLL_RECEIVE_BUFFER: usize = 1 << 20;

/// As [`serve_udp`], but the socket is taken off the reactor and read every `period` (shorter while
/// datagrams arrive fast, see [`poll_thresholds`]): whatever queued in the kernel meanwhile is
/// taken in one go. Arriving datagrams wake nothing.
pub(super) async fn serve_udp_polled(
    sh: &Shared,
    ctl: &mut Control,
    sock: UdpSocket,
    target: Option<SocketAddr>,
    rx: &mut Rx,
    period: Duration,
) -> End {
    let sock = match sock.into_std() {
        Ok(s) => s,
        Err(e) => return End::Lost(format!("udp socket: {e}")),
    };
    let silent_after = sh.tuning.silent;
    let mut peer: Option<SocketAddr> = None;
    let mut batch = udp_batch::UdpBatch::new();
    let buffer = match udp_batch::grow_receive_buffer(&sock, POLL_RECEIVE_BUFFER) {
        Ok(b) => b,
        Err(e) => {
            tracing::debug!("link {}: udp receive buffer left as it was: {e}", sh.index);
            0
        }
    };
    let (shrink_above, grow_below) = poll_thresholds(buffer);
    let mut fast_until = Instant::now();
    let mut last = Instant::now();
    let mut silent = false;
    let mut every = period;
    let epoch = sh
        .tuning
        .poll_epoch
        .unwrap_or_else(tokio::time::Instant::now);
    // The first poll at once (at the epoch, or on the grid's first point passed).
    let mut polls = GridTimer::new(epoch, every);
    loop {
        tokio::select! {
            biased;
            _ = wait_stop(&mut ctl.shutdown) => return End::Stop,
            _ = polls.tick() => {
                let mut taken = 0usize;
                let mut local = DecodeStats::default();
                let mut frames = Vec::new();
                loop {
                    let n = match batch.recv(&sock) {
                        Ok(n) => n,
                        Err(e) if transient_udp_error(&e) => break,
                        Err(e) => {
                            sh.merge(&local);
                            if !sh.offer_frames(&mut frames) {
                                return End::Stop;
                            }
                            return End::Lost(format!("udp receive failed: {e}"));
                        }
                    };
                    let time_us = now_us();
                    frames.reserve(n.min(sh.inbound.max_batch()));
                    for i in 0..n {
                        let (bytes, from) = batch.get(i);
                        if let Some(from) = from.filter(|f| target.is_none() && peer != Some(*f)) {
                            tracing::debug!("link {}: udp peer {from}", sh.index);
                            peer = Some(from);
                        }
                        taken += 1;
                        if !rx.take_bytes(sh, bytes, true, time_us, &mut local, &mut frames) {
                            return End::Stop;
                        }
                    }
                    if n < udp_batch::BATCH {
                        break;
                    }
                }
                sh.merge(&local);
                if !sh.offer_frames(&mut frames) {
                    return End::Stop;
                }
                if taken > shrink_above {
                    // Aim at about half the threshold per read at the rate just seen.
                    let aim = (shrink_above / 2) as u32;
                    every = (every * aim / taken as u32).max(POLL_MIN.min(period));
                    fast_until = Instant::now() + POLL_HOLD;
                } else if taken < grow_below && Instant::now() >= fast_until {
                    every = (every * 2).min(period);
                }
                polls.set_period(every);
                let got = taken > 0;
                if got {
                    last = Instant::now();
                    silent = false;
                } else if let Some(after) = silent_after {
                    if !silent && last.elapsed() >= after {
                        silent = true;
                        if !sh.status(LinkStatus::Silent { for_s: last.elapsed().as_secs_f64() }) {
                            return End::Stop;
                        }
                    }
                }
            }
            m = ctl.outbound.recv(), if ctl.outbound_open => match m {
                None => ctl.outbound_open = false,
                Some(bytes) => {
                    let sent = match (target, peer) {
                        (Some(_), _) => sock.send(&bytes).map(|_| ()),
                        (None, Some(p)) => sock.send_to(&bytes, p).map(|_| ()),
                        (None, None) => Err(std::io::Error::other("no peer has sent anything yet")),
                    };
                    if let Err(e) = sent {
                        tracing::trace!("link {}: udp send dropped: {e}", sh.index);
                        LinkCounters::add(&sh.counters.outbound_dropped, 1);
                    }
                }
            },
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Replays
