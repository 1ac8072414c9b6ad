//! Live links: opening udpin, udpout, tcpout and serial (dialled again with backoff when lost),
//! the tcpin server, and serving a byte stream.

use super::udp::{serve_udp, serve_udp_polled};
use super::*;

pub(super) trait Io: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Io for T {}

/// An open live connection.
pub(super) enum Conn {
    Stream {
        io: Box<dyn Io>,
        /// The local end of a TCP connection (none for a serial port).
        local: Option<SocketAddr>,
        desc: String,
        eof: &'static str,
    },
    Udp {
        sock: UdpSocket,
        /// udpout's target; `None` for udpin (reply to the last sender).
        target: Option<SocketAddr>,
        desc: String,
    },
}

impl Conn {
    /// What the link's `ready` entry says of this connection.
    fn opening(&self) -> LinkOpening {
        match self {
            Conn::Stream { local, desc, .. } => LinkOpening::Open {
                local: *local,
                detail: desc.clone(),
            },
            Conn::Udp { sock, desc, .. } => LinkOpening::Open {
                local: sock.local_addr().ok(),
                detail: desc.clone(),
            },
        }
    }
}

pub(super) const TCP_CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

pub(super) async fn open(addr: &Address) -> Result<Conn, String> {
    match addr {
        Address::UdpIn(a) => {
            let sock = UdpSocket::bind(a)
                .await
                .map_err(|e| format!("cannot bind udp {a}: {e}"))?;
            let local = sock
                .local_addr()
                .map(|l| l.to_string())
                .unwrap_or_else(|_| a.to_string());
            Ok(Conn::Udp {
                sock,
                target: None,
                desc: format!("listening on udp {local}"),
            })
        }
        Address::UdpOut(t) => {
            let local: SocketAddr = match (t.is_ipv4(), t.ip().is_loopback()) {
                (true, true) => "127.0.0.1:0",
                (true, false) => "0.0.0.0:0",
                (false, true) => "[::1]:0",
                (false, false) => "[::]:0",
            }
            .parse()
            .expect("literal socket address");
            let sock = UdpSocket::bind(local)
                .await
                .map_err(|e| format!("cannot bind udp {local}: {e}"))?;
            sock.connect(t)
                .await
                .map_err(|e| format!("cannot address udp {t}: {e}"))?;
            let local = sock.local_addr().map(|l| l.to_string()).unwrap_or_default();
            Ok(Conn::Udp {
                sock,
                target: Some(*t),
                desc: format!("udp to {t} from {local}"),
            })
        }
        Address::TcpOut(h) => {
            let s = match tokio::time::timeout(TCP_CONNECT_TIMEOUT, TcpStream::connect(h.as_str()))
                .await
            {
                Ok(Ok(s)) => s,
                Ok(Err(e)) => return Err(format!("cannot connect to tcp {h}: {e}")),
                Err(_) => return Err(format!("cannot connect to tcp {h}: timed out")),
            };
            let _ = s.set_nodelay(true);
            let local = s.local_addr().ok();
            let peer = s
                .peer_addr()
                .map(|p| p.to_string())
                .unwrap_or_else(|_| h.clone());
            Ok(Conn::Stream {
                io: Box::new(s),
                local,
                desc: format!("tcp {peer}"),
                eof: "connection closed by the remote end",
            })
        }
        Address::Serial { path, baud } => {
            use tokio_serial::SerialPortBuilderExt;
            let port = tokio_serial::new(path.as_str(), *baud)
                .open_native_async()
                .map_err(|e| format!("cannot open serial {path}: {e}"))?;
            Ok(Conn::Stream {
                io: Box::new(port),
                local: None,
                desc: format!("serial {path} at {baud} baud"),
                eof: "serial port closed (end of stream)",
            })
        }
        Address::TcpIn(_) | Address::File { .. } | Address::Sim { .. } => {
            Err(format!("{addr} is not a dialled link"))
        }
    }
}

/// udpin, udpout, tcpout, serial: open, serve, and on failure retry with backoff.
pub(super) async fn run_dialled(sh: &Shared, ctl: &mut Control, addr: &Address, payload: &Payload) {
    let t = &sh.tuning;
    let mut backoff = t.backoff_min;
    let mut first = true;
    let mut lost_reported = false;
    loop {
        if !first {
            LinkCounters::add(&sh.counters.reconnects, 1);
        }
        first = false;
        let Some(res) = guarded(ctl, &sh.counters, open(addr)).await else {
            return;
        };
        match res {
            Ok(conn) => {
                let up = Instant::now();
                let mut rx = Rx::new(payload);
                sh.opened(conn.opening());
                let end = match conn {
                    Conn::Stream { io, desc, eof, .. } => {
                        if !sh.status(LinkStatus::Connected(desc)) {
                            return;
                        }
                        serve_stream(sh, ctl, io, &mut rx, None, eof).await
                    }
                    Conn::Udp { sock, target, desc } => {
                        if !sh.status(LinkStatus::Connected(desc)) {
                            return;
                        }
                        match sh.tuning.udp_poll {
                            Some(period) => {
                                serve_udp_polled(sh, ctl, sock, target, &mut rx, period).await
                            }
                            None => serve_udp(sh, ctl, &sock, target, &mut rx).await,
                        }
                    }
                };
                match end {
                    End::Stop => return,
                    End::Lost(r) => {
                        if !sh.status(LinkStatus::Lost(r)) {
                            return;
                        }
                        lost_reported = true;
                    }
                }
                // A connection that lasted resets the backoff; one that flaps keeps growing it.
                if up.elapsed() >= t.backoff_max {
                    backoff = t.backoff_min;
                }
            }
            Err(reason) => {
                sh.opened(LinkOpening::Failed {
                    detail: reason.clone(),
                });
                if !lost_reported {
                    if !sh.status(LinkStatus::Lost(reason)) {
                        return;
                    }
                    lost_reported = true;
                } else {
                    tracing::trace!("link {}: still down: {reason}", sh.index);
                }
            }
        }
        if guarded(ctl, &sh.counters, tokio::time::sleep(backoff))
            .await
            .is_none()
        {
            return;
        }
        backoff = (backoff * 2).min(t.backoff_max);
    }
}

/// tcpin: listen on the given address; serve one client at a time (others are closed at once).
pub(super) async fn run_tcp_in(sh: &Shared, ctl: &mut Control, a: SocketAddr, payload: &Payload) {
    let t = &sh.tuning;
    let mut backoff = t.backoff_min;
    let mut lost_reported = false;
    let mut clients = 0u64;
    loop {
        let listener = match guarded(ctl, &sh.counters, TcpListener::bind(a)).await {
            None => return,
            Some(Ok(l)) => l,
            Some(Err(e)) => {
                let reason = format!("cannot listen on tcp {a}: {e}");
                sh.opened(LinkOpening::Failed {
                    detail: reason.clone(),
                });
                if !lost_reported {
                    if !sh.status(LinkStatus::Lost(reason)) {
                        return;
                    }
                    lost_reported = true;
                }
                if guarded(ctl, &sh.counters, tokio::time::sleep(backoff))
                    .await
                    .is_none()
                {
                    return;
                }
                backoff = (backoff * 2).min(t.backoff_max);
                LinkCounters::add(&sh.counters.reconnects, 1);
                continue;
            }
        };
        let local = listener.local_addr().ok();
        let shown = local.map_or_else(|| a.to_string(), |l| l.to_string());
        tracing::info!("link {}: listening on tcp {shown}", sh.index);
        sh.opened(LinkOpening::Open {
            local,
            detail: format!("listening on tcp {shown}"),
        });
        loop {
            let Some(acc) = guarded(ctl, &sh.counters, listener.accept()).await else {
                return;
            };
            let (stream, peer) = match acc {
                Ok(x) => x,
                Err(e) => {
                    // Transient (e.g. out of file descriptors): wait a little and accept again.
                    tracing::debug!("link {}: accept failed: {e}", sh.index);
                    let pause = tokio::time::sleep(Duration::from_millis(100));
                    if guarded(ctl, &sh.counters, pause).await.is_none() {
                        return;
                    }
                    continue;
                }
            };
            clients += 1;
            if clients > 1 {
                LinkCounters::add(&sh.counters.reconnects, 1);
            }
            let _ = stream.set_nodelay(true);
            if !sh.status(LinkStatus::Connected(format!("tcp client {peer}"))) {
                return;
            }
            let mut rx = Rx::new(payload);
            let eof = "client closed the connection";
            match serve_stream(sh, ctl, Box::new(stream), &mut rx, Some(&listener), eof).await {
                End::Stop => return,
                End::Lost(r) => {
                    if !sh.status(LinkStatus::Lost(format!(
                        "{r} ({peer}); waiting for a client"
                    ))) {
                        return;
                    }
                }
            }
        }
    }
}

/// Read a byte stream (TCP, serial) until it fails; write outbound bytes concurrently so a
/// stalled writer never stops the reader.
pub(super) async fn serve_stream(
    sh: &Shared,
    ctl: &mut Control,
    io: Box<dyn Io>,
    rx: &mut Rx,
    listener: Option<&TcpListener>,
    eof: &str,
) -> End {
    let (mut rd, mut wr) = tokio::io::split(io);
    let Control {
        shutdown,
        outbound,
        outbound_open,
    } = ctl;
    let silent_after = sh.tuning.silent;

    let reader = async {
        let mut buf = vec![0u8; 4096];
        let mut last = Instant::now();
        let mut silent = false;
        loop {
            let deadline = last + silent_after.unwrap_or(Duration::from_secs(3600));
            tokio::select! {
                r = rd.read(&mut buf) => match r {
                    Ok(0) => return End::Lost(eof.to_string()),
                    Ok(n) => {
                        last = Instant::now();
                        silent = false;
                        if !rx.on_bytes(sh, &buf[..n], false) {
                            return End::Stop;
                        }
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => return End::Lost(format!("read failed: {e}")),
                },
                _ = tokio::time::sleep_until(deadline), if silent_after.is_some() && !silent => {
                    silent = true;
                    let for_s = last.elapsed().as_secs_f64();
                    if !sh.status(LinkStatus::Silent { for_s }) {
                        return End::Stop;
                    }
                }
            }
        }
    };

    let writer = async {
        loop {
            if !*outbound_open {
                std::future::pending::<()>().await;
            }
            match outbound.recv().await {
                Some(bytes) => {
                    if let Err(e) = wr.write_all(&bytes).await {
                        LinkCounters::add(&sh.counters.outbound_dropped, 1);
                        return End::Lost(format!("write failed: {e}"));
                    }
                }
                None => *outbound_open = false,
            }
        }
    };

    // tcpin: one client at a time; close the others at once.
    let extra_clients = async {
        match listener {
            Some(l) => loop {
                match l.accept().await {
                    Ok((_s, peer)) => {
                        tracing::info!("link {}: refused a second tcp client {peer}", sh.index)
                    }
                    Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
                }
            },
            None => std::future::pending::<()>().await,
        }
    };

    tokio::select! {
        biased;
        _ = wait_stop(shutdown) => End::Stop,
        e = reader => e,
        e = writer => e,
        _ = extra_clients => End::Stop,
    }
}
