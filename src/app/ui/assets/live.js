// The live page: the state from the event stream (first the service's snapshot, then every
// JSON line, imucald.live/1), drawn at most every 100 ms.
(() => {
  const f = IMUDraw.fmt;
  const S = { progress: {}, calibration: {}, heading: null, attitude: null, trail: [], log: [], bands: [], lastEvent: 0,
    events: 0, connected: false };
  const sphere = IMUDraw.sphere(document.getElementById("sphere"));
  const $ = id => document.getElementById(id);
  const key = e => e.sensor + ":" + e.instance;

  function setState(s) {
    S.progress = {}; S.calibration = {};
    for (const p of s.progress || []) S.progress[key(p)] = p;
    for (const c of s.calibration || []) S.calibration[key(c)] = c;
    S.heading = s.heading; S.attitude = s.attitude;
    S.trail = s.trail || []; S.log = s.log || []; S.bands = s.bands || [];
    if (s.lines > 0) S.lastEvent = Date.now() - 1000 * (s.link.last_line_age_s || 0);
  }

  function firstMag() {
    const ks = Object.values(S.progress).filter(p => p.sensor === "mag").sort((a, b) => a.instance - b.instance);
    return ks[0];
  }

  function apply(e) {
    S.lastEvent = Date.now();
    document.body.dataset.events = String(++S.events);
    switch (e.type) {
      case "progress": {
        S.progress[key(e)] = e;
        const d = e.direction || [0, 0, 0], n = Math.hypot(d[0], d[1], d[2]);
        if (n > 0 && firstMag() === e) { S.trail.push(d.map(x => x / n)); if (S.trail.length > 600) S.trail.shift(); }
        break;
      }
      case "calibration": S.calibration[key(e)] = e; break;
      case "heading": S.heading = e; break;
      case "attitude": S.attitude = e; break;
      case "status": S.log.push(e); if (S.log.length > 50) S.log.shift(); break;
    }
    schedule();
  }

  // Which face of the vehicle to point along the Earth's field to fill the missing regions.
  function hint(p) {
    if (!p) return "Waiting for magnetometer progress.";
    const regs = IMUDraw.regions(S.bands), filled = IMUDraw.mask(p.regions, regs.length);
    const missing = regs.filter((r, i) => !filled[i]);
    if (p.filled_regions === 0) return "Turn the vehicle slowly through many orientations: regions are counted once the magnetometer's centre is known.";
    if (!missing.length) return "Every region is covered.";
    let m = [0, 0, 0];
    for (const r of missing) for (let k = 0; k < 3; k++) m[k] += r.centre[k] / missing.length;
    if (Math.hypot(m[0], m[1], m[2]) < 0.2) {
      // Gaps all around: the one farthest from where the field is now.
      const now = S.trail[S.trail.length - 1] || [0, 0, 1];
      let best = missing[0], bd = 2;
      for (const r of missing) { const d = r.centre[0] * now[0] + r.centre[1] * now[1] + r.centre[2] * now[2]; if (d < bd) { bd = d; best = r; } }
      m = best.centre;
    }
    const names = [["nose", "tail"], ["right side", "left side"], ["belly", "top"]];
    const order = [0, 1, 2].sort((a, b) => Math.abs(m[b]) - Math.abs(m[a]));
    const face = i => names[i][m[i] > 0 ? 0 : 1];
    let faces = "the " + face(order[0]);
    if (Math.abs(m[order[1]]) > 0.5 * Math.abs(m[order[0]])) faces += " and " + face(order[1]);
    return missing.length + " regions missing (orange). Point " + faces +
      " along the Earth's field (towards magnetic north, tilted down in the northern hemisphere), then turn slowly about that direction.";
  }

  function render() {
    const p = firstMag();
    sphere.set({ bands: S.bands, dirs: S.trail, trail: S.trail, regions: p ? p.regions : "", now: S.trail[S.trail.length - 1] });
    $("hint").textContent = hint(p);
    const prog = $("progress"); prog.textContent = "";
    for (const e of Object.values(S.progress).sort((a, b) => a.instance - b.instance)) {
      const id = "completion-" + e.instance;
      const bar = document.createElement("progress");
      bar.max = 100; bar.value = e.completion_pct; bar.id = "bar-" + e.instance;
      const lab = document.createElement("label"); lab.htmlFor = bar.id; lab.textContent = "Compass " + e.instance;
      const out = document.createElement("output"); out.id = id; out.setAttribute("for", bar.id);
      out.dataset.pct = String(e.completion_pct);
      out.textContent = f(e.completion_pct, 0) + " % (" + e.filled_regions + " of 100 regions)";
      const row = document.createElement("div"); row.className = "meter"; row.append(lab, bar, out);
      prog.append(row);
    }
    if (!prog.childNodes.length) prog.innerHTML = "<p class=\"muted\">No progress yet.</p>";
    const a = S.attitude || S.heading;
    if (a) {
      IMUDraw.dial($("dial"), a.heading_deg, a.roll_deg, a.pitch_deg);
      $("attitude").textContent = "Heading " + f(a.heading_deg, 1) + "° (" + (a.true_heading ? "true" : "magnetic") + "), roll " +
        f(a.roll_deg, 1) + "°, pitch " + f(a.pitch_deg, 1) + "°" + (S.attitude ? " (fused)" : "") + (a.mag_disturbed ? "; field disturbed" : "");
      $("dial").setAttribute("aria-label", $("attitude").textContent);
    }
    const cal = $("calibration");
    const cs = Object.values(S.calibration).sort((x, y) => x.instance - y.instance || x.sensor.localeCompare(y.sensor));
    if (cs.length) {
      const t = document.createElement("table");
      t.innerHTML = "<caption>Latest fit</caption><tr><th scope=\"col\">sensor</th><th scope=\"col\">compass</th><th scope=\"col\">status</th>" +
        "<th scope=\"col\">model</th><th scope=\"col\">offset ± 1-sigma</th><th scope=\"col\">RMS residual</th></tr>";
      for (const c of cs) {
        const tr = document.createElement("tr");
        const off = c.offset.map((x, i) => f(x, 2) + " ± " + f((c.offset_sigma || [])[i], 2)).join(", ");
        for (const [txt, cls] of [[c.sensor, ""], [String(c.instance), ""], [c.status === "ok" ? "ok" : "failed: " + (c.failure || "?"), c.status === "ok" ? "ok" : "bad"],
          [c.model, ""], [off, ""], [f(c.rms_residual, 3), ""]]) {
          const td = document.createElement("td"); td.textContent = txt; if (cls) td.className = cls; tr.append(td);
        }
        t.append(tr);
      }
      cal.textContent = ""; cal.append(t);
    }
    const log = $("log"); log.textContent = "";
    for (const e of S.log.slice(-50).reverse()) {
      const li = document.createElement("li"); li.className = e.level; li.textContent = e.level + ": " + e.text; log.append(li);
    }
    document.body.dataset.rendered = String((+document.body.dataset.rendered || 0) + 1);
  }

  // At most one render per 100 ms, the next one 100 ms after the last (not after the event).
  let pending = false, last = 0;
  function schedule() {
    if (pending) return;
    pending = true;
    setTimeout(() => { pending = false; last = performance.now(); render(); }, Math.max(0, last + 100 - performance.now()));
  }

  function linkText() {
    const age = (Date.now() - S.lastEvent) / 1000;
    $("link").textContent = !S.connected ? "Connection to the service lost; retrying…" : !S.lastEvent ? "Connected; waiting for data from the service." :
      age < 3 ? "Receiving live data." : "No data for " + f(age, 0) + " s (sources silent or ended).";
  }
  setInterval(linkText, 1000);

  const es = new EventSource("/api/events");
  es.addEventListener("state", e => { S.connected = true; setState(JSON.parse(e.data)); linkText(); schedule(); });
  es.onmessage = e => { try { apply(JSON.parse(e.data)); } catch (err) { /* not an event: skipped */ } };
  es.onerror = () => { S.connected = false; linkText(); };
})();
