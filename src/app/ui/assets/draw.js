"use strict";
// imucald's canvas drawing, shared by the live page and the HTML report: the sphere of field
// directions with the coverage regions, residual plots and the heading/attitude dial.
// Directions are body axes (x forward, y right, z down). The coverage regions are latitude bands
// of z (north = +z) split into equal spans of azimuth atan2(y, x) from -180 deg, as the service
// counts them; the bands come with the data.
const IMUDraw = (() => {
  const TAU = 2 * Math.PI;
  const COLORS = { missing: "rgba(213,94,0,0.62)", filled: "rgba(0,114,178,0.16)",
    front: "#0b2d6b", back: "rgba(90,90,90,0.35)", trail: "#0b2d6b", now: "#d81b60" };

  // Canvas sized for the screen's pixel density; returns its context in CSS pixels.
  function setup(canvas) {
    const dpr = window.devicePixelRatio || 1;
    const w = canvas.clientWidth || canvas.width, h = canvas.clientHeight || canvas.height;
    if (canvas.width !== Math.round(w * dpr)) {
      canvas.style.width = w + "px"; canvas.style.height = h + "px";
      canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    return { ctx, w, h };
  }

  // The regions of the bands: [{zlo, zhi, plo, phi, centre}] in region order.
  function regions(bands) {
    const out = [];
    let zhi = 1;
    for (const [zlo, n] of bands) {
      for (let k = 0; k < n; k++) {
        const plo = -Math.PI + TAU * k / n, phi = -Math.PI + TAU * (k + 1) / n;
        const zc = n === 1 ? (zlo > 0 ? 1 : -1) : (zlo + zhi) / 2, pc = (plo + phi) / 2;
        out.push({ zlo, zhi, plo, phi, n, centre: dir(zc, pc) });
      }
      zhi = zlo;
    }
    return out;
  }

  function dir(z, p) {
    const r = Math.sqrt(Math.max(0, 1 - z * z));
    return [r * Math.cos(p), r * Math.sin(p), z];
  }

  // 25 hex digits -> filled flags (region i: bit i%4 of digit i/4).
  function mask(hex, n) {
    const m = new Array(n).fill(false);
    if (!hex) return m;
    for (let i = 0; i < n; i++) {
      const d = parseInt(hex[i >> 2] || "0", 16);
      m[i] = ((d >> (i & 3)) & 1) === 1;
    }
    return m;
  }

  function outline(r) {
    const pts = [], steps = 8;
    if (r.n === 1) {
      const z = r.zlo > 0 ? r.zlo : r.zhi;
      for (let i = 0; i < 24; i++) pts.push(dir(z, TAU * i / 24));
      return pts;
    }
    for (let i = 0; i <= steps; i++) pts.push(dir(r.zlo, r.plo + (r.phi - r.plo) * i / steps));
    for (let i = 1; i < 3; i++) pts.push(dir(r.zlo + (r.zhi - r.zlo) * i / 3, r.phi));
    for (let i = steps; i >= 0; i--) pts.push(dir(r.zhi, r.plo + (r.phi - r.plo) * i / steps));
    for (let i = 2; i > 0; i--) pts.push(dir(r.zlo + (r.zhi - r.zlo) * i / 3, r.plo));
    return pts;
  }

  // A sphere view: drag (or arrow keys when focused) to turn it. data: {bands, dirs, regions
  // (hex), trail, now}.
  function sphere(canvas) {
    const view = { yaw: -0.65, pitch: 0.45 };
    let data = { bands: [], dirs: [], regions: "" };
    let regs = [], regsOf = null;
    function project(v, cx, cy, R) {
      // Seen from behind and above the vehicle: right = +y, up = -z, towards the viewer = -x.
      const X = v[1], Y = -v[2], Z = -v[0];
      const cyw = Math.cos(view.yaw), syw = Math.sin(view.yaw);
      const X1 = cyw * X + syw * Z, Z1 = -syw * X + cyw * Z;
      const cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
      const Y2 = cp * Y - sp * Z1, Z2 = sp * Y + cp * Z1;
      return [cx + R * X1, cy - R * Y2, Z2];
    }
    function draw() {
      const { ctx, w, h } = setup(canvas);
      const cx = w / 2, cy = h / 2, R = Math.min(w, h) * 0.40;
      if (regsOf !== data.bands) { regs = regions(data.bands || []); regsOf = data.bands; }
      const filled = mask(data.regions, regs.length);
      ctx.fillStyle = "#f7f9fb"; ctx.strokeStyle = "#8a949e"; ctx.lineWidth = 1;
      ctx.beginPath(); ctx.arc(cx, cy, R, 0, TAU); ctx.fill(); ctx.stroke();
      const dirs = data.dirs || [];
      ctx.fillStyle = COLORS.back;
      for (const d of dirs) {
        const p = project(d, cx, cy, R);
        if (p[2] < 0) ctx.fillRect(p[0] - 1, p[1] - 1, 2, 2);
      }
      regs.forEach((r, i) => {
        if (project(r.centre, cx, cy, R)[2] <= 0.02) return;
        ctx.beginPath();
        outline(r).forEach((v, k) => { const p = project(v, cx, cy, R); k ? ctx.lineTo(p[0], p[1]) : ctx.moveTo(p[0], p[1]); });
        ctx.closePath();
        ctx.fillStyle = filled[i] ? COLORS.filled : COLORS.missing;
        ctx.fill();
        ctx.strokeStyle = "rgba(255,255,255,0.9)"; ctx.stroke();
      });
      ctx.fillStyle = COLORS.front;
      for (const d of dirs) {
        const p = project(d, cx, cy, R);
        if (p[2] >= 0) ctx.fillRect(p[0] - 1.5, p[1] - 1.5, 3, 3);
      }
      const trail = data.trail || [];
      if (trail.length > 1) {
        ctx.strokeStyle = COLORS.trail; ctx.lineWidth = 1.5; ctx.beginPath();
        let on = false;
        for (const d of trail.slice(-60)) {
          const p = project(d, cx, cy, R);
          if (p[2] < 0) { on = false; continue; }
          on ? ctx.lineTo(p[0], p[1]) : ctx.moveTo(p[0], p[1]); on = true;
        }
        ctx.stroke();
      }
      if (data.now) {
        const p = project(data.now, cx, cy, R);
        ctx.fillStyle = COLORS.now; ctx.strokeStyle = "#fff"; ctx.lineWidth = 2;
        ctx.beginPath(); ctx.arc(p[0], p[1], p[2] >= 0 ? 7 : 4, 0, TAU); ctx.fill(); ctx.stroke();
      }
      ctx.font = "12px system-ui, sans-serif"; ctx.textAlign = "center"; ctx.textBaseline = "middle";
      for (const [v, name] of [[[1, 0, 0], "nose"], [[-1, 0, 0], "tail"], [[0, 1, 0], "right"],
        [[0, -1, 0], "left"], [[0, 0, 1], "belly"], [[0, 0, -1], "top"]]) {
        const p = project(v.map(x => x * 1.16), cx, cy, R);
        ctx.fillStyle = p[2] >= 0 ? "#111" : "#767676";
        ctx.fillText(name, p[0], p[1]);
      }
    }
    let drag = null;
    canvas.addEventListener("pointerdown", e => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
    canvas.addEventListener("pointermove", e => {
      if (!drag) return;
      view.yaw += (e.clientX - drag[0]) * 0.01;
      view.pitch = Math.max(-1.5, Math.min(1.5, view.pitch + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY]; draw();
    });
    canvas.addEventListener("pointerup", () => { drag = null; });
    canvas.addEventListener("keydown", e => {
      const k = { ArrowLeft: [-0.15, 0], ArrowRight: [0.15, 0], ArrowUp: [0, -0.15], ArrowDown: [0, 0.15] }[e.key];
      if (!k) return;
      e.preventDefault();
      view.yaw += k[0]; view.pitch = Math.max(-1.5, Math.min(1.5, view.pitch + k[1])); draw();
    });
    if (!canvas.hasAttribute("tabindex")) canvas.tabIndex = 0;
    return { set(d) { data = d; draw(); }, draw };
  }

  function fmt(x, digits) {
    if (x === null || x === undefined || !isFinite(x)) return "–";
    return Number(x).toFixed(digits === undefined ? 3 : digits);
  }

  // Residuals in fit order: points, zero line, +-RMS.
  function residuals(canvas, ys, units) {
    const { ctx, w, h } = setup(canvas);
    const L = 56, B = 30, T = 10, Rm = 10, pw = w - L - Rm, ph = h - T - B;
    let m = 0, sq = 0;
    for (const y of ys) { m = Math.max(m, Math.abs(y)); sq += y * y; }
    const rms = ys.length ? Math.sqrt(sq / ys.length) : 0;
    m = m > 0 ? m * 1.1 : 1;
    const X = i => L + pw * (ys.length > 1 ? i / (ys.length - 1) : 0.5), Y = y => T + ph * (0.5 - y / (2 * m));
    ctx.strokeStyle = "#8a949e"; ctx.lineWidth = 1; ctx.strokeRect(L, T, pw, ph);
    ctx.fillStyle = "#111"; ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "right"; ctx.textBaseline = "middle";
    for (const y of [m, 0, -m]) ctx.fillText(fmt(y, 3), L - 4, Y(y));
    ctx.textAlign = "center"; ctx.textBaseline = "top";
    ctx.fillText("fitted point (in fit order) · |calibrated| − radius, " + units, L + pw / 2, T + ph + 8);
    ctx.setLineDash([4, 3]); ctx.strokeStyle = "#d55e00";
    for (const y of [rms, -rms]) { ctx.beginPath(); ctx.moveTo(L, Y(y)); ctx.lineTo(L + pw, Y(y)); ctx.stroke(); }
    ctx.setLineDash([]); ctx.strokeStyle = "#555";
    ctx.beginPath(); ctx.moveTo(L, Y(0)); ctx.lineTo(L + pw, Y(0)); ctx.stroke();
    ctx.fillStyle = "#0b2d6b";
    ys.forEach((y, i) => ctx.fillRect(X(i) - 1, Y(y) - 1, 2, 2));
    return rms;
  }

  // Heading card (turns so the heading is at the top mark) around an attitude horizon.
  function dial(canvas, headingDeg, rollDeg, pitchDeg) {
    const { ctx, w, h } = setup(canvas);
    const cx = w / 2, cy = h / 2, R = Math.min(w, h) * 0.45, r = R * 0.68;
    ctx.save();
    ctx.beginPath(); ctx.arc(cx, cy, r, 0, TAU); ctx.clip();
    ctx.translate(cx, cy); ctx.rotate(-(rollDeg || 0) * Math.PI / 180);
    const off = Math.max(-r, Math.min(r, (pitchDeg || 0) / 45 * r));
    ctx.fillStyle = "#bcdcf2"; ctx.fillRect(-2 * r, -2 * r, 4 * r, 2 * r + off);
    ctx.fillStyle = "#d9c3a0"; ctx.fillRect(-2 * r, off, 4 * r, 2 * r);
    ctx.strokeStyle = "#fff"; ctx.lineWidth = 2; ctx.beginPath(); ctx.moveTo(-2 * r, off); ctx.lineTo(2 * r, off); ctx.stroke();
    ctx.restore();
    ctx.strokeStyle = "#111"; ctx.lineWidth = 3;
    ctx.beginPath(); ctx.moveTo(cx - r * 0.5, cy); ctx.lineTo(cx - r * 0.15, cy); ctx.lineTo(cx, cy + r * 0.1);
    ctx.lineTo(cx + r * 0.15, cy); ctx.lineTo(cx + r * 0.5, cy); ctx.stroke();
    ctx.lineWidth = 1; ctx.strokeStyle = "#8a949e";
    ctx.beginPath(); ctx.arc(cx, cy, R, 0, TAU); ctx.stroke();
    ctx.beginPath(); ctx.arc(cx, cy, r, 0, TAU); ctx.stroke();
    const hd = headingDeg || 0;
    ctx.font = "12px system-ui, sans-serif"; ctx.textAlign = "center"; ctx.textBaseline = "middle";
    for (let a = 0; a < 360; a += 10) {
      const t = (a - hd) * Math.PI / 180 - Math.PI / 2, big = a % 30 === 0;
      const r1 = R * (big ? 0.86 : 0.92);
      ctx.strokeStyle = "#333"; ctx.beginPath();
      ctx.moveTo(cx + R * Math.cos(t), cy + R * Math.sin(t)); ctx.lineTo(cx + r1 * Math.cos(t), cy + r1 * Math.sin(t)); ctx.stroke();
      if (big) {
        const label = { 0: "N", 90: "E", 180: "S", 270: "W" }[a] || String(a / 10);
        ctx.fillStyle = a === 0 ? "#a4260b" : "#111";
        ctx.fillText(label, cx + R * 0.77 * Math.cos(t), cy + R * 0.77 * Math.sin(t));
      }
    }
    ctx.fillStyle = "#d81b60";
    ctx.beginPath(); ctx.moveTo(cx, cy - R - 2); ctx.lineTo(cx - 7, cy - R - 12); ctx.lineTo(cx + 7, cy - R - 12); ctx.closePath(); ctx.fill();
  }

  return { sphere, residuals, dial, regions, mask, fmt };
})();
