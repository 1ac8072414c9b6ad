// The HTML report of a replay: built from the data embedded in the page (imucald.html/1).
(() => {
  const D = JSON.parse(document.getElementById("data").textContent);
  const R = D.report, f = IMUDraw.fmt;
  const main = document.getElementById("main");
  main.textContent = "";
  let uid = 0;

  function el(tag, attrs, ...kids) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
    for (const k of kids) if (k !== null && k !== undefined) e.append(k);
    return e;
  }
  function section(title, wide) {
    const id = "h" + (++uid);
    const s = el("section", { "aria-labelledby": id, class: wide ? "wide" : "" }, el("h2", { id }, title));
    main.append(s);
    return s;
  }
  function table(caption, head, rows) {
    const t = el("table", {}, el("caption", {}, caption));
    t.append(el("tr", {}, ...head.map(h => el("th", { scope: "col" }, h))));
    for (const r of rows) t.append(el("tr", {}, ...r.map((c, i) => i === 0 ? el("th", { scope: "row" }, c) : el("td", {}, c))));
    return t;
  }
  const vec = (v, d) => v ? "[" + v.map(x => f(x, d)).join(", ") + "]" : "–";
  const mat = m => m ? m.map(r => vec(r, 4)).join(" ") : "–";
  const name = { mag: "Magnetometer", accel: "Accelerometer" };

  // Input.
  const inp = R.input;
  const s0 = section("Input", true);
  const skipped = Object.entries(inp.skipped || {}).map(([k, v]) => k + " " + v).join(", ") || "none";
  s0.append(table("What was read", ["item", "value"], [
    ["file", inp.path || "–"], ["format", inp.format], ["samples", String(inp.samples)],
    ["duration", f(inp.duration_s, 1) + " s"], ["skipped", skipped],
    ["static poses", String((R.static_poses || []).length)], ["refits while reading", String((R.refits || []).length)],
  ]));

  // Per instance and sensor.
  for (const iv of D.views.instances) {
    const label = iv.instance ? "Instance " + iv.instance + (iv.compass_id !== null ? " (compass " + iv.compass_id + ")" : "") + (iv.primary ? ", primary" : "") : "Calibration";
    const s = section(label, true);
    for (const sv of iv.sensors) {
      const c = sv.calibration;
      s.append(el("h3", {}, name[sv.sensor] || sv.sensor));
      const ok = c.status === "ok";
      s.append(el("p", {}, el("span", { class: ok ? "ok" : "bad" }, ok ? "Calibrated" : "Failed: " + (c.failure || "?")),
        c.detail ? " — " + c.detail : ""));
      if (sv.plots_note) s.append(el("p", { class: "muted" }, sv.plots_note));
      s.append(table("Fitted values (calibrated = matrix · (raw − offset))", ["quantity", "value"], [
        ...(c.method ? [["method", c.method + (c.method_reason ? ": " + c.method_reason : "")]] : []),
        ["model", c.model], ["units", c.units], ["offset", vec(c.offset, 4)], ["offset 1-sigma", vec(c.offset_sigma, 4)],
        ["matrix", mat(c.matrix)], ["radius", f(c.radius, 4)], ["RMS residual", f(c.rms_residual, 4)],
        ["points used", String(c.samples_used)], ["outliers left out", String(c.outliers_rejected || 0)],
        ["iterations", String(c.iterations)],
      ]));
      for (const [which, v] of [["before calibration (about the raw centre)", sv.before], ["after calibration", sv.after]]) {
        if (!v) continue;
        const cv = el("canvas", { width: 320, height: 320, role: "img", tabindex: "0",
          "aria-label": name[sv.sensor] + " directions " + which + ": " + v.dirs.length + " points drawn, " + v.filled + " of 100 regions filled. Arrow keys turn the view." });
        s.append(el("figure", {}, cv, el("figcaption", {}, "Directions " + which + ": " + v.filled + " of 100 regions filled (orange: missing). Drag or use the arrow keys to turn.")));
        IMUDraw.sphere(cv).set({ bands: D.bands, dirs: v.dirs, regions: v.regions });
      }
      if (sv.residuals.length) {
        const cv = el("canvas", { width: 560, height: 220, role: "img" });
        const fig = el("figure", {}, cv);
        s.append(fig);
        const rms = IMUDraw.residuals(cv, sv.residuals, c.units);
        cv.setAttribute("aria-label", "Residuals of " + sv.residual_points + " fitted points, RMS " + f(rms, 4) + " " + c.units);
        fig.append(el("figcaption", {}, "Residual of each fitted point (" + sv.residual_points + " points" +
          (sv.residuals.length < sv.residual_points ? ", every " + Math.ceil(sv.residual_points / sv.residuals.length) + "th drawn" : "") +
          "); dashed: ± RMS " + f(rms, 4) + " " + c.units + "."));
      }
    }
    // The report's gyro record of this instance; without a bias, the report's reason instead.
    const gv = iv.gyro, g = gv && gv.calibration;
    if (g) {
      s.append(el("h3", {}, "Gyroscope"));
      const rows = [["status", g.status],
        gv.no_bias_reason ? ["bias", "none: " + gv.no_bias_reason] : ["bias", vec(g.bias, 5) + " " + g.units + " (1-sigma " + vec(g.bias_sigma, 5) + ")"],
        ["poses used", String(g.poses_used) + (g.poses_turning ? " (" + g.poses_turning + " left out as turning)" : "")]];
      if (g.scale) rows.push(["scale matrix", mat(g.scale.matrix)], ["gravity direction between poses", f(g.scale.rms_before_deg, 2) + " → " + f(g.scale.rms_after_deg, 2) + " deg"]);
      else if (g.scale_failure) rows.push(["scale", "not fitted: " + (g.scale_failure.detail || g.scale_failure.failure)]);
      s.append(table("Gyroscope bias from the static poses", ["quantity", "value"], rows));
    }
  }

  // Onboard calibration.
  if (R.onboard) {
    const o = R.onboard, s = section("Onboard calibration (" + o.stack + ")", true);
    const rows = [];
    for (const [kind, slots] of [["mag", o.mag], ["accel", o.accel]])
      for (const c of slots || []) rows.push([kind + " " + c.instance, vec(c.offset, 3), mat(c.matrix), (c.sources || []).join(", ")]);
    s.append(table("As the log's parameters record it, in imucald's model", ["slot", "offset", "matrix", "applies to"], rows));
    if ((o.undone || []).length) s.append(el("p", {}, "Undone before fitting: " + o.undone.join("; ")));
    if (o.comparison) {
      const c = o.comparison;
      s.append(table("imucald against the onboard calibration", ["quantity", "value"], [
        ["stream", c.source], ["offset difference", vec(c.offset_diff_ut, 3) + " uT"],
        ["heading difference", "RMS " + f(c.heading_diff_rms_deg, 2) + " deg, largest " + f(c.heading_diff_max_deg, 2) + " deg over " + c.samples + " samples"],
      ]));
    }
  }

  // Held-out quality: the plain answer first, then the figures per compass.
  if ((R.quality || []).length) {
    const s = section("Is it better than the vehicle's own?", true);
    const spread = h => h ? f(h.norm_spread_pct, 2) + " % / " + f(h.dip_spread_deg, 2) + " deg / " + f(h.heading_spread_deg, 2) + " deg (" + h.readings + " readings)" : "–";
    for (const q of R.quality) s.append(el("p", {}, el("strong", {}, q.instance + ": "), q.verdict));
    s.append(table("Fitted on alternate " + f(R.quality[0].block_s, 0) + " s blocks, scored on the others: spread of the field's norm / of its dip",
      ["compass", "imucald (" + R.quality[0].method + ")", "the vehicle's own"],
      R.quality.map(q => [q.instance, q.imucald ? spread(q.imucald) : "failed: " + (q.imucald_failure || "?"), spread(q.onboard)])));
  }

  // Diagnosis.
  if (D.diagnosis) {
    const d = D.diagnosis, s = section("Diagnosis", true);
    s.append(el("p", {}, "Effects found: " + ((d.found || []).join(", ") || "none")));
    s.append(table("Rounds", ["round", "decision", "effect", "detail"],
      (d.rounds || []).map((r, i) => [String(i + 1), String(r.decision), r.effect || "–", r.detail || ""])));
    const rows = [];
    for (const [eff, params] of Object.entries(d.effects || {}))
      for (const [p, v] of Object.entries(params || {})) rows.push([eff + "." + p, f(v.value, 5) + " ± " + f(v.sigma, 5) + " " + (v.unit || "")]);
    if (rows.length) s.append(table("Fitted effects", ["parameter", "value ± 1-sigma"], rows));
    s.append(el("p", {}, "Held-out RMS (expected-noise units): before " + f(d.rms_before, 3) + ", after " + f(d.rms_after, 3)));
  }
  document.body.setAttribute("data-ready", "1");
})();
