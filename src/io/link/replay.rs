//! Replays (`file:`, `sim:`): recorded frames and samples paced by their own timestamps, waiting
//! for room in the queue instead of dropping.

use super::*;

/// Longest pause a replay makes for one gap in its timestamps (recorded time), s.
pub(crate) const MAX_REPLAY_GAP_S: f64 = 10.0;

/// Maps recorded times onto the clock at `speed` (0 = no waiting). Backwards steps do not wait;
/// gaps longer than [`MAX_REPLAY_GAP_S`] are shortened to it.
pub(super) struct Pacer {
    speed: f64,
    start: Instant,
    last: Option<f64>,
    elapsed: f64,
}

impl Pacer {
    fn new(speed: f64) -> Pacer {
        Pacer {
            speed,
            start: Instant::now(),
            last: None,
            elapsed: 0.0,
        }
    }

    fn deadline(&mut self, t_s: f64) -> Option<Instant> {
        if !(self.speed > 0.0) || !t_s.is_finite() {
            return None;
        }
        let Some(last) = self.last.replace(t_s) else {
            self.start = Instant::now();
            return None;
        };
        self.elapsed += (t_s - last).clamp(0.0, MAX_REPLAY_GAP_S);
        Some(self.start + secs(self.elapsed / self.speed))
    }

    /// Wait until `t_s` is due. False on shutdown.
    async fn wait(&mut self, sh: &Shared, ctl: &mut Control, t_s: f64) -> bool {
        let due = self.deadline(t_s);
        self.wait_until(sh, ctl, due).await
    }

    /// Wait until `due` (a [`Pacer::deadline`]; none: no wait). False on shutdown.
    async fn wait_until(&self, sh: &Shared, ctl: &mut Control, due: Option<Instant>) -> bool {
        match due {
            Some(d) if d > Instant::now() => {
                guarded(ctl, &sh.counters, tokio::time::sleep_until(d))
                    .await
                    .is_some()
            }
            _ => true,
        }
    }
}

/// True when a CSV payload's file has no header row (its first line starts with a number).
pub(super) fn headerless(text: &str) -> bool {
    text.lines()
        .find(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .and_then(|l| l.split(',').next())
        .is_some_and(|c| c.trim().parse::<f64>().is_ok())
}

pub(super) async fn run_file(
    sh: &Shared,
    ctl: &mut Control,
    path: &std::path::Path,
    speed: f64,
    payload: &Payload,
) {
    let p = path.to_path_buf();
    let read = blocking(sh, ctl, move || {
        let raw = std::fs::read(&p).map_err(|e| format!("cannot read {}: {e}", p.display()))?;
        let data = decode::maybe_gunzip(&raw)
            .map_err(|e| format!("cannot decompress {}: {e}", p.display()))?
            .into_owned();
        Ok((raw.len(), data))
    })
    .await;
    let (size, data) = match read {
        None => return,
        Some(Ok(x)) => x,
        Some(Err(e)) => {
            if deliver_status(sh, ctl, LinkStatus::Lost(e)).await {
                deliver_status(sh, ctl, LinkStatus::Ended).await;
            }
            return;
        }
    };
    LinkCounters::add(&sh.counters.bytes_in, size as u64);
    let name = path.display().to_string();
    let lower = name.to_ascii_lowercase();
    let format = decode::detect_format(&data).or_else(|| {
        if lower.ends_with(".tlog") {
            Some(decode::Format::Tlog)
        } else if lower.ends_with(".csv") || lower.ends_with(".csv.gz") {
            Some(decode::Format::Csv)
        } else {
            None
        }
    });
    let pace = if speed > 0.0 {
        format!("at {speed}x")
    } else {
        "as fast as possible".to_string()
    };
    let ok = match format {
        Some(decode::Format::Tlog) => {
            deliver_status(
                sh,
                ctl,
                LinkStatus::Connected(format!("replaying tlog {name} {pace}")),
            )
            .await
                && replay_tlog(sh, ctl, &data, speed).await
        }
        Some(decode::Format::Csv) => {
            let text = String::from_utf8_lossy(&data);
            let mut mapping = decode::CsvMapping::default();
            let owned;
            let text: &str = match payload {
                Payload::Csv { fields, scales } => {
                    mapping.scales = scales.clone();
                    if headerless(&text) {
                        owned = format!("{}\n{text}", fields.join(","));
                        &owned
                    } else {
                        &text
                    }
                }
                _ => &text,
            };
            let mut stats = DecodeStats::default();
            match decode::decode_csv(text, &mapping, &mut stats) {
                Ok(samples) => {
                    sh.merge(&stats);
                    deliver_status(
                        sh,
                        ctl,
                        LinkStatus::Connected(format!("replaying csv {name} {pace}")),
                    )
                    .await
                        && replay_samples(sh, ctl, samples, speed).await
                }
                Err(e) => deliver_status(sh, ctl, LinkStatus::Lost(format!("{name}: {e}"))).await,
            }
        }
        Some(decode::Format::Bin | decode::Format::Ulg) | None => {
            let msg = format!("{name}: neither a .tlog nor a CSV with a header row (flight-controller logs: use `imucald replay`)");
            deliver_status(sh, ctl, LinkStatus::Lost(msg)).await
        }
    };
    if ok {
        deliver_status(sh, ctl, LinkStatus::Ended).await;
    }
}

/// Replay a tlog's records paced by their timestamps; the records due together (all of them at
/// speed 0) go as one item, up to the queue's batch size.
pub(super) async fn replay_tlog(sh: &Shared, ctl: &mut Control, data: &[u8], speed: f64) -> bool {
    let mut records = TlogRecords::new(data);
    let mut pacer = Pacer::new(speed);
    let mut batch: Vec<TimedFrame> = Vec::new();
    let max = sh.inbound.max_batch();
    while let Some((ts, frame)) = records.next() {
        // Publish the records and skips so far.
        sh.merge(&std::mem::take(&mut records.stats));
        let due = pacer.deadline(ts as f64 * 1e-6);
        let wait = due.is_some_and(|d| d > Instant::now());
        if (wait || batch.len() >= max)
            && !(deliver_frames(sh, ctl, &mut batch).await && pacer.wait_until(sh, ctl, due).await)
        {
            sh.merge(&records.stats);
            return false;
        }
        LinkCounters::add(&sh.counters.frames_in, 1);
        batch.push(TimedFrame { time_us: ts, frame });
    }
    sh.merge(&records.stats);
    deliver_frames(sh, ctl, &mut batch).await
}

/// Queue a replay's frames so far, if any, waiting for room. False on shutdown or when the
/// service is gone.
pub(super) async fn deliver_frames(
    sh: &Shared,
    ctl: &mut Control,
    batch: &mut Vec<TimedFrame>,
) -> bool {
    if batch.is_empty() {
        return true;
    }
    let frames = std::mem::take(batch);
    let link = sh.index;
    deliver(sh, ctl, Inbound::Frames { link, frames }).await
}

/// Emit samples paced by their `t_s`. False on shutdown.
pub(super) async fn replay_samples(
    sh: &Shared,
    ctl: &mut Control,
    samples: Vec<Sample>,
    speed: f64,
) -> bool {
    let mut pacer = Pacer::new(speed);
    for sample in samples {
        if !pacer.wait(sh, ctl, sample.t_s).await {
            return false;
        }
        LinkCounters::add(&sh.counters.samples_in, 1);
        let item = Inbound::Sample {
            link: sh.index,
            sample,
        };
        if !deliver(sh, ctl, item).await {
            return false;
        }
    }
    true
}

pub(super) async fn run_sim(sh: &Shared, ctl: &mut Control, scenario: &str, seed: u64, speed: f64) {
    let name = scenario.to_string();
    let made = blocking(sh, ctl, move || {
        let sc = crate::sim::named::scenario(&name).map_err(|e| e.to_string())?;
        Ok(crate::sim::simulate(&sc, seed).samples)
    })
    .await;
    let samples = match made {
        None => return,
        Some(Ok(s)) => s,
        Some(Err(e)) => {
            if deliver_status(sh, ctl, LinkStatus::Lost(e)).await {
                deliver_status(sh, ctl, LinkStatus::Ended).await;
            }
            return;
        }
    };
    let mut stats = DecodeStats::default();
    for s in &samples {
        stats.records += 1;
        stats.count_sample(s);
    }
    sh.merge(&stats);
    let pace = if speed > 0.0 {
        format!("at {speed}x")
    } else {
        "as fast as possible".to_string()
    };
    let desc = format!(
        "simulating {scenario} (seed {seed}, {} samples) {pace}",
        samples.len()
    );
    if deliver_status(sh, ctl, LinkStatus::Connected(desc)).await
        && replay_samples(sh, ctl, samples, speed).await
    {
        deliver_status(sh, ctl, LinkStatus::Ended).await;
    }
}
