//! Link addresses: `udpin:`, `udpout:`, `tcpout:`, `tcpin:`, `serial:`, `file:`, `sim:`, parsed
//! with errors that name the form expected, and written back the same way.

use crate::error::Error;
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;

/// Where a link reads from (and writes to).
#[derive(Debug, Clone, PartialEq)]
pub enum Address {
    /// `udpin:IP:PORT`: bind this address; replies go to the last sender.
    UdpIn(SocketAddr),
    /// `udpout:IP:PORT`: send to this address; receive on the same socket.
    UdpOut(SocketAddr),
    /// `tcpout:HOST:PORT`: connect (reconnect with backoff).
    TcpOut(String),
    /// `tcpin:IP:PORT`: listen, one client at a time.
    TcpIn(SocketAddr),
    /// `serial:PATH:BAUD`.
    Serial { path: String, baud: u32 },
    /// `file:PATH[?speed=N]`: a .tlog or a CSV (.csv, .csv.gz). Speed 0 = as fast as possible;
    /// 1 (the default) = recorded pace.
    File { path: PathBuf, speed: f64 },
    /// `sim:SCENARIO[?seed=N&speed=N]`: a built-in scenario name or a path to a scenario .toml.
    Sim {
        scenario: String,
        seed: u64,
        speed: f64,
    },
}

/// The accepted address forms, for error messages.
pub(crate) const ADDRESS_FORMS: &str =
    "udpin:IP:PORT, udpout:IP:PORT, tcpout:HOST:PORT, tcpin:IP:PORT, \
serial:PATH:BAUD, file:PATH[?speed=N], sim:SCENARIO[?seed=N&speed=N]";

/// Seed of `sim:` when the address names none (the same as `imucald simulate`).
pub(crate) const DEFAULT_SIM_SEED: u64 = 1;

fn source_err(s: &str, why: impl std::fmt::Display) -> Error {
    Error::Config {
        key: "source".into(),
        message: format!("`{s}`: {why} (accepted forms: {ADDRESS_FORMS})"),
    }
}

fn parse_socket(s: &str, scheme: &str, rest: &str) -> Result<SocketAddr, Error> {
    rest.parse::<SocketAddr>().map_err(|_| {
        source_err(
            s,
            format!(
                "{scheme}: needs an IP address and port such as {scheme}:127.0.0.1:14550 \
                 (IPv6: {scheme}:[::1]:14550; host names are not resolved here)"
            ),
        )
    })
}

/// Split `PATH?k=v&k=v` into the path and its options. Unknown keys and bad numbers are errors.
fn split_query<'a>(
    s: &str,
    rest: &'a str,
    allowed: &[&str],
) -> Result<(&'a str, BTreeMap<String, String>), Error> {
    let (path, query) = match rest.rfind('?') {
        Some(i) => (&rest[..i], Some(&rest[i + 1..])),
        None => (rest, None),
    };
    let mut opts = BTreeMap::new();
    if let Some(q) = query {
        for kv in q.split('&').filter(|kv| !kv.is_empty()) {
            let Some((k, v)) = kv.split_once('=') else {
                return Err(source_err(
                    s,
                    format!("option `{kv}` needs a value (`key=value`)"),
                ));
            };
            if !allowed.contains(&k) {
                return Err(source_err(
                    s,
                    format!("unknown option `{k}` (known: {})", allowed.join(", ")),
                ));
            }
            opts.insert(k.to_string(), v.to_string());
        }
    }
    Ok((path, opts))
}

fn parse_speed(s: &str, v: Option<&String>) -> Result<f64, Error> {
    match v {
        None => Ok(1.0),
        Some(v) => match v.parse::<f64>() {
            Ok(x) if x.is_finite() && x >= 0.0 => Ok(x),
            _ => Err(source_err(
                s,
                format!("speed `{v}` must be a number >= 0 (0 = as fast as possible, 1 = recorded pace)"),
            )),
        },
    }
}

impl Address {
    /// Parse a link address. Errors are `Error::Config { key: "source" }` naming the accepted forms.
    pub fn parse(s: &str) -> Result<Address, Error> {
        let s = s.trim();
        let Some((scheme, rest)) = s.split_once(':') else {
            return Err(source_err(s, "no scheme"));
        };
        match scheme {
            "udpin" => Ok(Address::UdpIn(parse_socket(s, scheme, rest)?)),
            "udpout" => Ok(Address::UdpOut(parse_socket(s, scheme, rest)?)),
            "tcpin" => Ok(Address::TcpIn(parse_socket(s, scheme, rest)?)),
            "tcpout" => {
                let ok = rest
                    .rsplit_once(':')
                    .is_some_and(|(h, p)| !h.is_empty() && p.parse::<u16>().is_ok_and(|p| p > 0));
                if ok {
                    Ok(Address::TcpOut(rest.to_string()))
                } else {
                    Err(source_err(
                        s,
                        "tcpout: needs HOST:PORT such as tcpout:127.0.0.1:5760 (port 1-65535)",
                    ))
                }
            }
            "serial" => {
                let Some((path, baud)) = rest.rsplit_once(':') else {
                    return Err(source_err(
                        s,
                        "serial: needs a port and a baud rate such as serial:/dev/ttyUSB0:115200",
                    ));
                };
                let baud = baud.parse::<u32>().ok().filter(|b| *b > 0);
                match baud {
                    Some(baud) if !path.is_empty() => Ok(Address::Serial {
                        path: path.to_string(),
                        baud,
                    }),
                    _ => Err(source_err(
                        s,
                        "serial: needs a port and a baud rate such as serial:/dev/ttyUSB0:115200",
                    )),
                }
            }
            "file" => {
                let (path, opts) = split_query(s, rest, &["speed"])?;
                if path.is_empty() {
                    return Err(source_err(s, "file: needs a path such as file:flight.tlog"));
                }
                Ok(Address::File {
                    path: PathBuf::from(path),
                    speed: parse_speed(s, opts.get("speed"))?,
                })
            }
            "sim" => {
                let (name, opts) = split_query(s, rest, &["seed", "speed"])?;
                crate::sim::named::check_name(name)
                    .map_err(|e| source_err(s, format!("sim: {e}")))?;
                let seed = match opts.get("seed") {
                    None => DEFAULT_SIM_SEED,
                    Some(v) => v.parse::<u64>().map_err(|_| {
                        source_err(s, format!("seed `{v}` must be a whole number >= 0"))
                    })?,
                };
                Ok(Address::Sim {
                    scenario: name.to_string(),
                    seed,
                    speed: parse_speed(s, opts.get("speed"))?,
                })
            }
            other => Err(source_err(s, format!("unknown scheme `{other}:`"))),
        }
    }

    /// True for replays (`file:`, `sim:`), which wait for room on the inbound channel.
    pub fn is_replay(&self) -> bool {
        matches!(self, Address::File { .. } | Address::Sim { .. })
    }
}

impl std::str::FromStr for Address {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Address::parse(s)
    }
}

impl std::fmt::Display for Address {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Address::UdpIn(a) => write!(f, "udpin:{a}"),
            Address::UdpOut(a) => write!(f, "udpout:{a}"),
            Address::TcpOut(h) => write!(f, "tcpout:{h}"),
            Address::TcpIn(a) => write!(f, "tcpin:{a}"),
            Address::Serial { path, baud } => write!(f, "serial:{path}:{baud}"),
            Address::File { path, speed } => {
                write!(f, "file:{}", path.display())?;
                if *speed != 1.0 {
                    write!(f, "?speed={speed}")?;
                }
                Ok(())
            }
            Address::Sim {
                scenario,
                seed,
                speed,
            } => {
                write!(f, "sim:{scenario}")?;
                let mut sep = '?';
                if *seed != DEFAULT_SIM_SEED {
                    write!(f, "{sep}seed={seed}")?;
                    sep = '&';
                }
                if *speed != 1.0 {
                    write!(f, "{sep}speed={speed}")?;
                }
                Ok(())
            }
        }
    }
}
