// swarmdrop console: the page. Plain JavaScript and canvas, nothing loaded from elsewhere.
//
// One websocket to the console server (swarmdrop/console/protocol.py): binary frames with
// packed arrays (viewed in place with typed arrays), JSON meta/status/result messages.
// Drawing runs on requestAnimationFrame and is batched: one path per phase colour for the
// vehicles, one for the trails, one for the slots; no DOM work per frame. The vehicle table
// and the health panel update at 2 Hz, and the table shows one page of rows.
// window.SDConsole exposes what the tests and the bench read (frame times, what was drawn).
"use strict";
(function () {
  const PHASE_COLOURS = ["#8a8f98", "#f0a030", "#e8d44d", "#4aa3ff", "#3ccf7a", "#b080ff", "#ff4d4d"];
  const MAGIC = 0x31464453, HEADER = 32;
  const FLAG_PLAYING = 2, FLAG_LIVE_CLOCK = 4;
  const TRAIL_N = 32, TRAIL_DT = 0.25, STALE_S = 1.0, LABELS_MAX = 150, TIMES_KEPT = 1200;
  const $ = (id) => document.getElementById(id);

  const S = {
    meta: null, frame: null, frameAt: 0, status: null, ws: null, connected: false, retry: 500,
    view: { cn: 0, ce: 0, scale: 4, fitted: false, touched: false }, sideAxis: "n",
    trail: { cap: 0, buf: null, head: 0, count: 0, lastT: NaN },
    sel: -1, page: 0, perPage: 25, pick: false, pickWps: [], reqId: 0,
    frameTimes: [], drawTimes: [], lastRaf: 0, drawn: 0, onScreen: 0, frames: 0, framesDrawn: 0,
    drag: null, px: new Float32Array(0), py: new Float32Array(0), scrubbing: false, lastSeek: 0,
    dirty: true,
  };
  // Redraw only when something changed (a frame, the view, the page's size): the page costs
  // nothing between frames, and the frame rate the server sends (20 Hz) is the vehicles' rate.
  const touch = () => { S.dirty = true; };
  window.addEventListener("resize", touch);

  // ------------------------------------------------------------------ websocket
  function connect() {
    const ws = new WebSocket(`ws://${location.host}/ws`);
    ws.binaryType = "arraybuffer";
    S.ws = ws;
    ws.onopen = () => { S.connected = true; S.retry = 500; setConn(); };
    ws.onclose = () => {
      S.connected = false; setConn();
      setTimeout(connect, S.retry); S.retry = Math.min(5000, S.retry * 2);
    };
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") onText(ev.data); else onFrame(ev.data);
    };
  }

  function send(obj) {
    if (S.ws && S.ws.readyState === 1) { S.ws.send(JSON.stringify(obj)); return true; }
    return false;
  }

  function setConn() {
    const c = $("conn");
    c.textContent = S.connected ? "connected" : "disconnected";
    c.className = "badge " + (S.connected ? "on" : "off");
  }

  function onText(text) {
    let m;
    try { m = JSON.parse(text); } catch (e) { return; }
    if (m.type === "meta") onMeta(m);
    else if (m.type === "status") onStatus(m);
    else if (m.type === "result") onResult(m);
  }

  function parseFrame(buf) {
    if (buf.byteLength < HEADER) return null;
    const dv = new DataView(buf);
    if (dv.getUint32(0, true) !== MAGIC) return null;
    const n = dv.getUint32(4, true);
    const need = HEADER + 4 * (3 * n * 3 + 4 * n) + 4 * n + 3 * n;
    if (buf.byteLength < need) return null;
    let off = HEADER;
    const f32 = (k) => { const a = new Float32Array(buf, off, k); off += 4 * k; return a; };
    const fr = {
      n, t: dv.getFloat64(8, true), tgo: dv.getFloat64(16, true), seq: dv.getUint32(24, true),
      flags: dv.getUint32(28, true),
    };
    fr.pos = f32(3 * n); fr.vel = f32(3 * n); fr.yaw = f32(n); fr.age = f32(n); fr.slot = f32(3 * n);
    fr.ferr = f32(n); fr.rate = f32(n);
    fr.plan = new Uint32Array(buf, off, n); off += 4 * n;
    fr.phase = new Uint8Array(buf, off, n); off += n;
    fr.vflags = new Uint8Array(buf, off, n); off += n;
    fr.known = new Uint8Array(buf, off, n);
    return fr;
  }

  function onFrame(buf) {
    const fr = parseFrame(buf);
    if (!fr) return;
    S.frame = fr; S.frameAt = performance.now(); S.frames++; S.dirty = true;
    if (fr.n !== S.px.length) { S.px = new Float32Array(fr.n); S.py = new Float32Array(fr.n); }
    addTrail(fr);
    if (!S.view.fitted && !S.view.touched) fit(false);
    if ($("follow").checked) follow();
  }

  // ------------------------------------------------------------------ trails
  function addTrail(fr) {
    const T = S.trail;
    if (fr.n > T.cap) {
      T.cap = Math.max(16, Math.ceil(fr.n * 1.25));
      T.buf = new Float32Array(T.cap * TRAIL_N * 2).fill(NaN); T.head = 0; T.count = 0; T.lastT = NaN;
    }
    if (!(fr.t >= T.lastT - 0.5)) { T.buf.fill(NaN); T.head = 0; T.count = 0; T.lastT = NaN; }  // a seek back
    if (!isNaN(T.lastT) && fr.t - T.lastT < TRAIL_DT) return;
    T.lastT = isFinite(fr.t) ? fr.t : T.lastT;
    const base = T.head * T.cap * 2, buf = T.buf, pos = fr.pos;
    for (let i = 0; i < fr.n; i++) {
      buf[base + 2 * i] = pos[3 * i]; buf[base + 2 * i + 1] = pos[3 * i + 1];
    }
    for (let i = fr.n; i < T.cap; i++) { buf[base + 2 * i] = NaN; buf[base + 2 * i + 1] = NaN; }
    T.head = (T.head + 1) % TRAIL_N; T.count = Math.min(TRAIL_N, T.count + 1);
  }

  // ------------------------------------------------------------------ meta, status, results
  function onMeta(m) {
    S.meta = m; S.dirty = true;
    const replay = m.mode === "replay";
    $("mode").textContent = replay ? "REPLAY" : "LIVE";
    $("mode").className = "badge " + (replay ? "replay" : "on");
    $("mission").textContent = m.mission && m.mission.name ? `mission ${m.mission.name}` : "no mission";
    $("signing").textContent = `signing ${m.signing}`;
    $("replaybar").hidden = !replay;
    if (replay && m.replay) {
      const sel = $("speed");
      if (!sel.options.length) {
        for (const v of m.replay.speeds) { const o = document.createElement("option"); o.value = v; o.textContent = `${v}×`; sel.appendChild(o); }
      }
      sel.value = String(m.replay.speed);
      $("rsource").textContent = m.replay.source || "";
      updateReplay(m.replay);
    }
    const c = m.commands || { enabled: false, why: "" };
    const st = $("cmdstate");
    st.textContent = c.enabled ? (c.signed ? "signed" : "enabled") : "off";
    st.className = "badge " + (c.enabled ? "on" : "off");
    st.title = c.enabled ? (c.note || "") : (c.why || "");
    for (const b of document.querySelectorAll("button.cmd")) {
      b.disabled = !c.enabled; b.title = c.enabled ? "" : `commands are off: ${c.why || ""}`;
    }
    $("goto-pick").disabled = !c.enabled;
    const lg = $("legend");
    lg.textContent = "";
    (m.phases || []).forEach((name, k) => {
      const s = document.createElement("span");
      const i = document.createElement("i"); i.style.background = PHASE_COLOURS[k];
      s.appendChild(i); s.appendChild(document.createTextNode(name)); lg.appendChild(s);
    });
  }

  function fmt(x, d) { return x === null || x === undefined || !isFinite(x) ? "–" : Number(x).toFixed(d); }

  function onStatus(m) {
    S.status = m;
    const h = m.health || {};
    $("h-heard").textContent = h.n !== undefined ? `${h.heard} / ${h.n}` : "–";
    $("h-stale").textContent = fmt(h.stale, 0);
    $("h-ferr").textContent = h.ferr_max_m === null || h.ferr_max_m === undefined ? "–" : `${fmt(h.ferr_max_m, 2)} m`;
    $("h-ferrmean").textContent = h.ferr_mean_m === null || h.ferr_mean_m === undefined ? "–" : `${fmt(h.ferr_mean_m, 2)} m`;
    $("h-sep").textContent = h.min_sep_m === null || h.min_sep_m === undefined ? "–" : `${fmt(h.min_sep_m, 2)} m`;
    $("h-seppair").textContent = h.min_sep_pair ? h.min_sep_pair.join("–") : "–";
    $("h-age50").textContent = h.age_p50_s === null || h.age_p50_s === undefined ? "–" : `${fmt(h.age_p50_s, 3)} s`;
    $("h-age99").textContent = h.age_p99_s === null || h.age_p99_s === undefined ? "–" : `${fmt(h.age_p99_s, 3)} s`;
    $("h-cspeed").textContent = h.centre_speed_mps === null || h.centre_speed_mps === undefined ? "–" : `${fmt(h.centre_speed_mps, 2)} m/s`;
    $("h-cclimb").textContent = h.centre_vspeed_mps === null || h.centre_vspeed_mps === undefined ? "–" : `${fmt(h.centre_vspeed_mps, 2)} m/s`;
    const pb = $("phasebar");
    pb.textContent = "";
    if (h.phases) {
      Object.entries(h.phases).forEach(([name, count], k) => {
        const s = document.createElement("span"); s.dataset.phase = name;
        const i = document.createElement("i"); i.style.background = PHASE_COLOURS[k];
        s.appendChild(i); s.appendChild(document.createTextNode(`${name} ${count}`)); pb.appendChild(s);
      });
      if (h.unknown) { const s = document.createElement("span"); s.textContent = `unheard ${h.unknown}`; pb.appendChild(s); }
    }
    const c = m.counters;
    $("counters").textContent = c ? `states ${c.states} · rejected ${c.rejected} · bad frames ${c.bad_frames}` +
      (c.unsigned !== undefined ? ` · unsigned ${c.unsigned} · forged ${c.bad_signature}` : "") : "";
    renderPlans(m);
    if (m.replay && !S.scrubbing) updateReplay(m.replay);
    renderTable();
  }

  function renderPlans(m) {
    const tb = $("plantab").tBodies[0];
    tb.textContent = "";
    const holders = m.holders || {};
    const plans = [{ seq: 0, kind: "mission" }].concat(m.plans || []);
    const seen = new Set();
    for (const p of plans) {
      if (seen.has(p.seq)) continue;
      seen.add(p.seq);
      const h = holders[String(p.seq)];
      if (p.seq === 0 && !h) continue;
      const tr = document.createElement("tr"); tr.dataset.seq = p.seq;
      const ids = h ? h.ids.slice(0, 20).join(",") + (h.count > Math.min(20, h.ids.length) ? "…" : "") : "";
      for (const text of [String(p.seq), p.kind, h ? `${h.count}: ${ids}` : "0"]) {
        const td = document.createElement("td"); td.textContent = text; tr.appendChild(td);
      }
      tb.appendChild(tr);
    }
  }

  function updateReplay(r) {
    $("play").textContent = r.playing ? "❚❚" : "▶";
    const span = Math.max(1e-9, r.t1 - r.t0);
    if (!S.scrubbing) $("scrub").value = String(Math.round(1000 * (r.t - r.t0) / span));
    $("rtime").textContent = `t ${r.t.toFixed(1)} s / ${r.t1.toFixed(1)} s`;
    if ($("speed").value !== String(r.speed)) $("speed").value = String(r.speed);
  }

  function logCmd(text, ok) {
    const d = document.createElement("div");
    d.className = ok ? "ok" : "err";
    d.textContent = `${new Date().toLocaleTimeString()} ${text}`;
    const log = $("cmdlog");
    log.insertBefore(d, log.firstChild);
    while (log.childNodes.length > 30) log.removeChild(log.lastChild);
  }

  function onResult(m) {
    if (m.replay) updateReplay(m.replay);
    if (m.id && String(m.id).startsWith("c")) logCmd(m.text || (m.ok ? "ok" : "refused"), m.ok);
  }

  // ------------------------------------------------------------------ view
  function canvasSize(cv) {
    const dpr = window.devicePixelRatio || 1;
    const w = cv.clientWidth, h = cv.clientHeight;
    if (cv.width !== Math.round(w * dpr) || cv.height !== Math.round(h * dpr)) {
      cv.width = Math.round(w * dpr); cv.height = Math.round(h * dpr);
    }
    const ctx = cv.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    return [ctx, w, h];
  }

  function bounds() {
    const fr = S.frame;
    let nmin = Infinity, nmax = -Infinity, emin = Infinity, emax = -Infinity;
    const take = (n, e) => { if (isFinite(n) && isFinite(e)) { nmin = Math.min(nmin, n); nmax = Math.max(nmax, n); emin = Math.min(emin, e); emax = Math.max(emax, e); } };
    if (fr) for (let i = 0; i < fr.n; i++) take(fr.pos[3 * i], fr.pos[3 * i + 1]);
    if (!isFinite(nmin) && S.meta && S.meta.mission) {
      for (const w of S.meta.mission.waypoints || []) take(w[0], w[1]);
      for (const o of S.meta.mission.obstacles || []) take(o.c[0], o.c[1]);
    }
    return isFinite(nmin) ? [nmin, nmax, emin, emax] : null;
  }

  function fit(userAsked) {
    const b = bounds();
    const cv = $("map");
    if (!b || !cv.clientWidth) return;
    const [nmin, nmax, emin, emax] = b;
    const w = cv.clientWidth, h = cv.clientHeight;
    const span = Math.max(nmax - nmin, emax - emin, 10);
    S.view.cn = (nmin + nmax) / 2; S.view.ce = (emin + emax) / 2;
    S.view.scale = Math.min(200, Math.max(0.01, 0.8 * Math.min(w, h) / span));
    if (S.frame && S.frame.known.some((k) => k)) S.view.fitted = true;
    if (userAsked) S.view.touched = false;
  }

  function follow() {
    const fr = S.frame; let n = 0, sn = 0, se = 0;
    for (let i = 0; i < fr.n; i++) {
      const a = fr.pos[3 * i], b = fr.pos[3 * i + 1];
      if (isFinite(a) && isFinite(b)) { sn += a; se += b; n++; }
    }
    if (n) { S.view.cn = sn / n; S.view.ce = se / n; }
  }

  function niceStep(minMetres) {
    const p = Math.pow(10, Math.floor(Math.log10(minMetres)));
    for (const m of [1, 2, 5, 10]) if (m * p >= minMetres) return m * p;
    return 10 * p;
  }

  function toScreen(n, e, w, h) { return [w / 2 + (e - S.view.ce) * S.view.scale, h / 2 - (n - S.view.cn) * S.view.scale]; }
  function toMission(x, y, w, h) { return [S.view.cn - (y - h / 2) / S.view.scale, S.view.ce + (x - w / 2) / S.view.scale]; }

  function drawGrid(ctx, w, h) {
    const step = niceStep(60 / S.view.scale);
    const [nTop, eLeft] = toMission(0, 0, w, h), [nBot, eRight] = toMission(w, h, w, h);
    ctx.strokeStyle = "#1f2731"; ctx.lineWidth = 1; ctx.beginPath();
    for (let e = Math.ceil(eLeft / step) * step; e <= eRight; e += step) { const x = Math.round(toScreen(0, e, w, h)[0]) + 0.5; ctx.moveTo(x, 0); ctx.lineTo(x, h); }
    for (let n = Math.ceil(nBot / step) * step; n <= nTop; n += step) { const y = Math.round(toScreen(n, 0, w, h)[1]) + 0.5; ctx.moveTo(0, y); ctx.lineTo(w, y); }
    ctx.stroke();
    ctx.strokeStyle = "#33404f"; ctx.beginPath();  // the origin's axes
    const [ox, oy] = toScreen(0, 0, w, h);
    ctx.moveTo(ox, 0); ctx.lineTo(ox, h); ctx.moveTo(0, oy); ctx.lineTo(w, oy); ctx.stroke();
    ctx.fillStyle = "#5d6b7b"; ctx.font = "11px system-ui, sans-serif";
    for (let e = Math.ceil(eLeft / step) * step; e <= eRight; e += step) ctx.fillText(`E ${+e.toFixed(3)}`, toScreen(0, e, w, h)[0] + 3, h - 4);
    for (let n = Math.ceil(nBot / step) * step; n <= nTop; n += step) ctx.fillText(`N ${+n.toFixed(3)}`, 4, toScreen(n, 0, w, h)[1] - 3);
    ctx.fillText(`grid ${step} m`, w - 70, h - 18);
  }

  function drawMission(ctx, w, h) {
    const m = S.meta && S.meta.mission;
    if (!m) return;
    if (m.geofence) {
      const [x0, y0] = toScreen(m.geofence.max[0], m.geofence.min[1], w, h);
      const [x1, y1] = toScreen(m.geofence.min[0], m.geofence.max[1], w, h);
      ctx.setLineDash([6, 4]); ctx.strokeStyle = "#c06060"; ctx.lineWidth = 1.5;
      ctx.strokeRect(x0, y0, x1 - x0, y1 - y0); ctx.setLineDash([]);
      ctx.fillStyle = "#c06060"; ctx.fillText("geofence", x0 + 4, y0 + 12);
    }
    for (const o of m.obstacles || []) {
      const [x, y] = toScreen(o.c[0], o.c[1], w, h);
      ctx.beginPath(); ctx.arc(x, y, Math.max(2, o.r * S.view.scale), 0, 2 * Math.PI);
      ctx.fillStyle = "rgba(255, 80, 80, 0.18)"; ctx.fill(); ctx.strokeStyle = "#d05050"; ctx.lineWidth = 1.5; ctx.stroke();
      ctx.fillStyle = "#e08080"; ctx.fillText(`obstacle r ${o.r} m, alt ${(-o.c[2]).toFixed(0)} m`, x + 4, y - Math.max(2, o.r * S.view.scale) - 4);
    }
    const wps = m.waypoints || [];
    if (wps.length) {
      ctx.setLineDash([4, 4]); ctx.strokeStyle = "#55708d"; ctx.lineWidth = 1; ctx.beginPath();
      wps.forEach((p, k) => { const [x, y] = toScreen(p[0], p[1], w, h); if (k) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
      ctx.stroke(); ctx.setLineDash([]);
      ctx.fillStyle = "#7fa0c4";
      wps.forEach((p, k) => { const [x, y] = toScreen(p[0], p[1], w, h); ctx.fillRect(x - 3, y - 3, 6, 6); ctx.fillText(`wp${k}`, x + 5, y + 12); });
    }
    if (S.pickWps.length) {
      ctx.strokeStyle = "#f0a030"; ctx.fillStyle = "#f0a030"; ctx.beginPath();
      S.pickWps.forEach((p, k) => { const [x, y] = toScreen(p[0], p[1], w, h); if (k) ctx.lineTo(x, y); else ctx.moveTo(x, y); });
      ctx.stroke();
      S.pickWps.forEach((p, k) => { const [x, y] = toScreen(p[0], p[1], w, h); ctx.fillRect(x - 3, y - 3, 6, 6); ctx.fillText(`goto ${k + 1}`, x + 5, y - 5); });
    }
  }

  function drawTrails(ctx, fr, w, h) {
    const T = S.trail;
    if (!T.count || !$("showtrails").checked) return;
    const buf = T.buf, cap = T.cap, sc = S.view.scale, cx = w / 2 - S.view.ce * sc, cy = h / 2 + S.view.cn * sc;
    ctx.strokeStyle = "rgba(150, 170, 195, 0.35)"; ctx.lineWidth = 1; ctx.beginPath();
    const first = (T.head - T.count + TRAIL_N) % TRAIL_N;
    for (let i = 0; i < fr.n; i++) {
      let pen = false;
      for (let j = 0; j < T.count; j++) {
        const o = (((first + j) % TRAIL_N) * cap + i) * 2;
        const n = buf[o], e = buf[o + 1];
        if (n !== n || e !== e) { pen = false; continue; }
        const x = cx + e * sc, y = cy - n * sc;
        if (pen) ctx.lineTo(x, y); else { ctx.moveTo(x, y); pen = true; }
      }
      if (pen && S.px[i] === S.px[i]) ctx.lineTo(S.px[i], S.py[i]);
    }
    ctx.stroke();
  }

  function drawSlots(ctx, fr, w, h) {
    if (!$("showslots").checked) return;
    const sc = S.view.scale, cx = w / 2 - S.view.ce * sc, cy = h / 2 + S.view.cn * sc, r = 3;
    ctx.strokeStyle = "rgba(200, 210, 225, 0.55)"; ctx.lineWidth = 1; ctx.beginPath();
    for (let i = 0; i < fr.n; i++) {
      const n = fr.slot[3 * i], e = fr.slot[3 * i + 1];
      if (n !== n || e !== e) continue;
      const x = cx + e * sc, y = cy - n * sc;
      if (x < -5 || y < -5 || x > w + 5 || y > h + 5) continue;
      ctx.moveTo(x + r, y); ctx.arc(x, y, r, 0, 2 * Math.PI);
    }
    ctx.stroke();
  }

  function screenPositions(fr, w, h) {
    const sc = S.view.scale, cx = w / 2 - S.view.ce * sc, cy = h / 2 + S.view.cn * sc;
    const px = S.px, py = S.py, pos = fr.pos;
    let on = 0;
    for (let i = 0; i < fr.n; i++) {
      const n = pos[3 * i], e = pos[3 * i + 1];
      if (n !== n || e !== e) { px[i] = NaN; py[i] = NaN; continue; }
      const x = cx + e * sc, y = cy - n * sc;
      px[i] = x; py[i] = y;
      if (x >= -10 && y >= -10 && x <= w + 10 && y <= h + 10) on++;
    }
    return on;
  }

  function drawVehicles(ctx, fr, w, h) {
    const L = Math.max(6, Math.min(13, S.view.scale * 1.2));
    const px = S.px, py = S.py, yaw = fr.yaw, age = fr.age, phase = fr.phase;
    const ca = Math.cos(2.45), sa = Math.sin(2.45);
    let drawn = 0;
    for (let pass = 0; pass < 2; pass++) {
      ctx.globalAlpha = pass ? 0.35 : 1;
      for (let p = 0; p < PHASE_COLOURS.length; p++) {
        ctx.beginPath();
        let any = false;
        for (let i = 0; i < fr.n; i++) {
          if (phase[i] !== p) continue;
          const x = px[i], y = py[i];
          if (x !== x || x < -20 || y < -20 || x > w + 20 || y > h + 20) continue;
          const stale = !(age[i] <= STALE_S);
          if ((pass === 1) !== stale) continue;
          const s = Math.sin(yaw[i]), c = Math.cos(yaw[i]);
          // tip along the heading (east = sin, north = cos; screen y grows southwards)
          ctx.moveTo(x + L * s, y - L * c);
          ctx.lineTo(x + 0.7 * L * (s * ca + c * sa), y - 0.7 * L * (c * ca - s * sa));
          ctx.lineTo(x + 0.7 * L * (s * ca - c * sa), y - 0.7 * L * (c * ca + s * sa));
          ctx.closePath();
          any = true; drawn++;
        }
        if (any) { ctx.fillStyle = PHASE_COLOURS[p]; ctx.fill(); }
      }
    }
    ctx.globalAlpha = 1;
    if (S.sel >= 0 && S.sel < fr.n && px[S.sel] === px[S.sel]) {
      ctx.strokeStyle = "#ffffff"; ctx.lineWidth = 2; ctx.beginPath(); ctx.arc(px[S.sel], py[S.sel], L + 5, 0, 2 * Math.PI); ctx.stroke();
    }
    if ($("showlabels").checked && S.onScreen <= LABELS_MAX) {
      ctx.fillStyle = "#e6edf5"; ctx.font = "11px system-ui, sans-serif";
      for (let i = 0; i < fr.n; i++) {
        const x = px[i], y = py[i];
        if (x !== x || x < -20 || y < -20 || x > w + 20 || y > h + 20) continue;
        ctx.fillText(String(i), x + L * 0.8, y - L * 0.8);
      }
    }
    return drawn;
  }

  function drawMap() {
    const cv = $("map");
    const [ctx, w, h] = canvasSize(cv);
    ctx.fillStyle = "#0d1117"; ctx.fillRect(0, 0, w, h);
    drawGrid(ctx, w, h);
    drawMission(ctx, w, h);
    const fr = S.frame;
    if (!fr) { S.drawn = 0; return; }
    S.onScreen = screenPositions(fr, w, h);
    drawSlots(ctx, fr, w, h);
    drawTrails(ctx, fr, w, h);
    S.drawn = drawVehicles(ctx, fr, w, h);
  }

  function drawSide() {
    const cv = $("side");
    const [ctx, w, h] = canvasSize(cv);
    ctx.fillStyle = "#0d1117"; ctx.fillRect(0, 0, w, h);
    const fr = S.frame, m = S.meta && S.meta.mission;
    const axisN = S.sideAxis === "n", ax = axisN ? 0 : 1;
    const centre = axisN ? S.view.cn : S.view.ce, sc = S.view.scale;
    let amin = 0, amax = 10;
    if (m && m.ground_z_m !== null && m.ground_z_m !== undefined) amin = Math.min(amin, -m.ground_z_m);
    if (fr) for (let i = 0; i < fr.n; i++) { const a = -fr.pos[3 * i + 2]; if (a === a) { amin = Math.min(amin, a); amax = Math.max(amax, a); } }
    if (m) for (const o of m.obstacles || []) { amax = Math.max(amax, -o.c[2] + o.r); }
    amax += 3; amin -= 1;
    const vs = (h - 18) / Math.max(1, amax - amin);
    const X = (v) => w / 2 + (v - centre) * sc, Y = (a) => h - 12 - (a - amin) * vs;
    const step = niceStep(30 / vs);
    ctx.strokeStyle = "#1f2731"; ctx.lineWidth = 1; ctx.beginPath(); ctx.fillStyle = "#5d6b7b"; ctx.font = "11px system-ui, sans-serif";
    for (let a = Math.ceil(amin / step) * step; a <= amax; a += step) { const y = Math.round(Y(a)) + 0.5; ctx.moveTo(0, y); ctx.lineTo(w, y); ctx.fillText(`${+a.toFixed(2)} m`, 4, y - 2); }
    ctx.stroke();
    if (m && m.ground_z_m !== null && m.ground_z_m !== undefined) {
      ctx.strokeStyle = "#6b5a3a"; ctx.lineWidth = 2; ctx.beginPath(); ctx.moveTo(0, Y(-m.ground_z_m)); ctx.lineTo(w, Y(-m.ground_z_m)); ctx.stroke();
    }
    if (m) {
      for (const o of m.obstacles || []) {
        ctx.beginPath(); ctx.ellipse(X(o.c[ax]), Y(-o.c[2]), Math.max(1, o.r * sc), Math.max(1, o.r * vs), 0, 0, 2 * Math.PI);
        ctx.fillStyle = "rgba(255, 80, 80, 0.18)"; ctx.fill(); ctx.strokeStyle = "#d05050"; ctx.stroke();
      }
    }
    ctx.fillStyle = "#5d6b7b"; ctx.fillText(axisN ? "north →" : "east →", w - 60, h - 2);
    if (!fr) return;
    for (let p = 0; p < PHASE_COLOURS.length; p++) {
      ctx.beginPath(); let any = false;
      for (let i = 0; i < fr.n; i++) {
        if (fr.phase[i] !== p) continue;
        const v = fr.pos[3 * i + ax], a = -fr.pos[3 * i + 2];
        if (v !== v || a !== a) continue;
        const x = X(v), y = Y(a);
        if (x < -5 || x > w + 5) continue;
        ctx.moveTo(x + 3, y); ctx.arc(x, y, 3, 0, 2 * Math.PI); any = true;
      }
      if (any) { ctx.fillStyle = PHASE_COLOURS[p]; ctx.fill(); }
    }
  }

  function drawClock() {
    const fr = S.frame;
    if (!fr || !isFinite(fr.t)) { $("clock").textContent = ""; $("tgo").textContent = ""; return; }
    const live = (fr.flags & FLAG_LIVE_CLOCK) !== 0;
    $("clock").textContent = live ? new Date(fr.t * 1000).toISOString().replace("T", " ").slice(0, 21) + " UTC"
      : `t ${fr.t.toFixed(1)} s`;
    $("tgo").textContent = isFinite(fr.tgo) ? (fr.t < fr.tgo ? `transit in ${(fr.tgo - fr.t).toFixed(1)} s` : `transit +${(fr.t - fr.tgo).toFixed(1)} s`) : "no transit start yet";
  }

  function frameLoop(now) {
    if (S.lastRaf) { S.frameTimes.push(now - S.lastRaf); if (S.frameTimes.length > TIMES_KEPT) S.frameTimes.splice(0, S.frameTimes.length - TIMES_KEPT); }
    S.lastRaf = now;
    if (S.dirty) {
      S.dirty = false;
      const t0 = performance.now();
      try {
        drawMap(); drawSide(); drawClock();
        if (S.flushDraw) {  // (the bench: read a pixel back, so the timing includes the rasterisation)
          $("map").getContext("2d").getImageData(0, 0, 1, 1); $("side").getContext("2d").getImageData(0, 0, 1, 1);
        }
      } catch (e) { S.lastError = String(e); }
      const d = performance.now() - t0;
      S.drawTimes.push(d); if (S.drawTimes.length > TIMES_KEPT) S.drawTimes.splice(0, S.drawTimes.length - TIMES_KEPT);
      S.framesDrawn++;
    }
    requestAnimationFrame(frameLoop);
  }

  // ------------------------------------------------------------------ the vehicle table (2 Hz, one page)
  let rows = [];
  function ensureRows() {
    const tb = $("vtab").tBodies[0];
    while (rows.length < S.perPage) {
      const tr = document.createElement("tr");
      const cells = [];
      for (let k = 0; k < 9; k++) { const td = document.createElement("td"); tr.appendChild(td); cells.push(td); }
      cells[1].className = "phase";
      tr.addEventListener("click", () => { const id = Number(tr.dataset.id); if (id >= 0) { S.sel = id; renderTable(); touch(); } });
      tb.appendChild(tr); rows.push({ tr, cells, key: "" });
    }
  }

  function tableOrder() {
    const fr = S.frame; if (!fr) return [];
    const ap = S.status && S.status.ap;
    const names = (S.meta && S.meta.phases) || [];
    const q = $("filter").value.trim().toLowerCase();
    let idx = [];
    for (let i = 0; i < fr.n; i++) {
      if (q) {
        const mode = ap && ap.mode[i] ? ap.mode[i].toLowerCase() : "";
        const ph = fr.known[i] ? (names[fr.phase[i]] || "") : "unheard";
        if (!(String(i) === q || ph.startsWith(q) || (mode && mode.includes(q)))) continue;
      }
      idx.push(i);
    }
    if ($("sort").value === "problems") {
      const score = (i) => (!fr.known[i] ? 1e6 : 0) + (fr.phase[i] === 6 ? 1e5 : 0) + (fr.age[i] > STALE_S ? 1e4 + fr.age[i] : 0) + (fr.ferr[i] === fr.ferr[i] ? fr.ferr[i] : 0);
      idx.sort((a, b) => score(b) - score(a));
    }
    return idx;
  }

  function renderTable() {
    ensureRows();
    const fr = S.frame, ap = S.status && S.status.ap;
    const names = (S.meta && S.meta.phases) || [];
    const idx = tableOrder();
    const pages = Math.max(1, Math.ceil(idx.length / S.perPage));
    if (S.sel >= 0 && S.jumpToSel) { const at = idx.indexOf(S.sel); if (at >= 0) S.page = Math.floor(at / S.perPage); S.jumpToSel = false; }
    S.page = Math.min(S.page, pages - 1);
    $("pageinfo").textContent = `${S.page + 1} / ${pages} (${idx.length})`;
    for (let r = 0; r < S.perPage; r++) {
      const row = rows[r], i = idx[S.page * S.perPage + r];
      if (i === undefined || !fr) { row.tr.hidden = true; row.tr.dataset.id = "-1"; continue; }
      row.tr.hidden = false; row.tr.dataset.id = String(i);
      const known = fr.known[i] === 1;
      const armed = ap ? (ap.armed[i] === 1 ? "yes" : ap.armed[i] === 0 ? "no" : "–") : "–";
      const vals = [String(i), known ? (names[fr.phase[i]] || String(fr.phase[i])) : "unheard",
        known ? fmt(fr.age[i], 2) : "–", fmt(fr.rate[i], 1), fmt(fr.ferr[i], 2), known ? String(fr.plan[i]) : "–",
        ap && ap.mode[i] ? ap.mode[i] : "–", armed, ap && ap.battery[i] !== null && ap.battery[i] !== undefined ? `${ap.battery[i]} %` : "–"];
      const key = vals.join("|") + (S.sel === i ? "*" : "");
      if (key === row.key) continue;
      row.key = key;
      vals.forEach((v, k) => { if (row.cells[k].lastChild && row.cells[k].lastChild.nodeType === 3 && k !== 1) row.cells[k].lastChild.nodeValue = v; else { row.cells[k].textContent = ""; if (k === 1 && known) { const ic = document.createElement("i"); ic.style.background = PHASE_COLOURS[fr.phase[i]] || "#888"; row.cells[k].appendChild(ic); } row.cells[k].appendChild(document.createTextNode(v)); } });
      row.tr.className = (S.sel === i ? "sel " : "") + (known && fr.age[i] > STALE_S ? "stale " : "") + (known && fr.phase[i] === 6 ? "failed" : "");
    }
  }

  // ------------------------------------------------------------------ commands
  function parseIds(text) {
    const t = text.trim().toLowerCase();
    if (!t || t === "all") return null;
    const ids = t.split(/[\s,;]+/).filter(Boolean).map(Number);
    if (ids.some((x) => !Number.isInteger(x) || x < 0)) throw new Error("vehicle ids are whole numbers from 0");
    return ids;
  }

  function parseWaypoints(text) {
    const wps = text.split(";").map((s) => s.trim()).filter(Boolean).map((s) => s.split(/[\s,]+/).filter(Boolean).map(Number));
    if (!wps.length || wps.some((w) => w.length !== 3 || w.some((x) => !isFinite(x)))) throw new Error("waypoints: N,E,D; N,E,D … in metres");
    return wps;
  }

  function commandRequest(cmd) {
    const r = { type: "command", cmd };
    if (cmd === "goto") { r.waypoints = parseWaypoints($("goto-wps").value); r.speed = Number($("goto-speed").value); }
    else if (cmd === "formation") {
      r.shape = $("f-shape").value; r.radius = Number($("f-radius").value); r.spacing = Number($("f-spacing").value);
      r.rotation_deg = Number($("f-rotation").value);
    } else if (cmd === "exclude") { r.ids = [Number($("x-id").value)]; r.land = $("x-how").value === "land"; }
    else if (cmd === "rejoin") { r.ids = [Number($("x-id").value)]; }
    else if (cmd === "land") { r.ids = parseIds($("land-ids").value); }
    return r;
  }

  function confirmThen(text, go) {
    const dlg = $("confirm");
    $("confirmtext").textContent = text;
    const yes = $("confirmyes"), no = $("confirmno");
    const done = (ok) => { yes.onclick = null; no.onclick = null; dlg.close(); if (ok) go(); else logCmd("cancelled", false); };
    yes.onclick = () => done(true); no.onclick = () => done(false);
    dlg.showModal();
  }

  function issue(cmd) {
    let r;
    try { r = commandRequest(cmd); } catch (e) { logCmd(`${cmd.toUpperCase()}: ${e.message}`, false); return; }
    const go = () => {
      r.id = `c${++S.reqId}`;
      if (cmd === "land" || cmd === "abort") r.confirm = true;
      if (!send(r)) logCmd("not connected", false);
    };
    if (cmd === "land") {
      const who = r.ids ? `vehicles ${r.ids.join(", ")}` : "EVERY vehicle";
      confirmThen(`LAND ${who}? They descend and disarm where they are.`, go);
    } else if (cmd === "abort") {
      confirmThen("ABORT? Every agent hands its vehicle to the autopilot's own Hold/Loiter and stops commanding it.", go);
    } else go();
  }

  // ------------------------------------------------------------------ input
  function nearestVehicle(x, y, maxPx) {
    const fr = S.frame; if (!fr) return -1;
    let best = -1, bd = maxPx * maxPx;
    for (let i = 0; i < fr.n; i++) {
      const dx = S.px[i] - x, dy = S.py[i] - y, d = dx * dx + dy * dy;
      if (d < bd) { bd = d; best = i; }
    }
    return best;
  }

  function readout(x, y) {
    const cv = $("map"), w = cv.clientWidth, h = cv.clientHeight;
    const [n, e] = toMission(x, y, w, h);
    let text = `N ${n.toFixed(1)} m  E ${e.toFixed(1)} m`;
    const o = S.meta && S.meta.mission && S.meta.mission.origin;
    if (o) { const g = window.SDGeo.nedToGeodetic(n, e, 0, o); text += `  ·  ${window.SDGeo.formatLatLon(g[0], g[1])}`; }
    const k = nearestVehicle(x, y, 12);
    if (k >= 0 && S.frame) {
      const fr = S.frame, names = (S.meta && S.meta.phases) || [];
      const sp = Math.hypot(fr.vel[3 * k], fr.vel[3 * k + 1]);
      text += `  ·  vehicle ${k} ${names[fr.phase[k]] || ""} alt ${(-fr.pos[3 * k + 2]).toFixed(1)} m ${sp.toFixed(1)} m/s`;
    }
    text += `  ·  1 px = ${(1 / S.view.scale).toPrecision(2)} m`;
    $("readout").textContent = text;
    S.readout = { n, e, text };
  }

  function zoomAt(x, y, factor) {
    const cv = $("map"), w = cv.clientWidth, h = cv.clientHeight;
    const [n, e] = toMission(x, y, w, h);
    S.view.scale = Math.min(400, Math.max(0.005, S.view.scale * factor));
    const [n2, e2] = toMission(x, y, w, h);
    S.view.cn += n - n2; S.view.ce += e - e2; S.view.touched = true; S.dirty = true;
  }

  function bind() {
    const cv = $("map");
    cv.addEventListener("wheel", (ev) => { ev.preventDefault(); const r = cv.getBoundingClientRect(); zoomAt(ev.clientX - r.left, ev.clientY - r.top, Math.exp(-ev.deltaY * 0.0015)); }, { passive: false });
    cv.addEventListener("mousedown", (ev) => { const r = cv.getBoundingClientRect(); S.drag = { x: ev.clientX - r.left, y: ev.clientY - r.top, cn: S.view.cn, ce: S.view.ce, moved: false }; });
    window.addEventListener("mouseup", (ev) => {
      const d = S.drag; S.drag = null;
      if (!d || d.moved) return;
      const r = cv.getBoundingClientRect(), x = ev.clientX - r.left, y = ev.clientY - r.top;
      if (S.pick) {
        const [n, e] = toMission(x, y, cv.clientWidth, cv.clientHeight);
        S.pickWps.push([+n.toFixed(1), +e.toFixed(1), -Number($("goto-alt").value || 10)]);
        $("goto-wps").value = S.pickWps.map((p) => p.join(",")).join("; "); touch();
      } else {
        const k = nearestVehicle(x, y, 14);
        S.sel = k; S.jumpToSel = true; if (k >= 0) $("x-id").value = String(k); renderTable(); touch();
      }
    });
    cv.addEventListener("mousemove", (ev) => {
      const r = cv.getBoundingClientRect(), x = ev.clientX - r.left, y = ev.clientY - r.top;
      if (S.drag) {
        const dx = x - S.drag.x, dy = y - S.drag.y;
        if (Math.abs(dx) + Math.abs(dy) > 3) S.drag.moved = true;
        if (S.drag.moved) { S.view.ce = S.drag.ce - dx / S.view.scale; S.view.cn = S.drag.cn + dy / S.view.scale; S.view.touched = true; S.dirty = true; }
      }
      readout(x, y);
    });
    $("fit").onclick = () => { fit(true); touch(); };
    for (const id of ["showlabels", "showtrails", "showslots", "follow"]) $(id).addEventListener("change", touch);
    $("zoomin").onclick = () => { const c = $("map"); zoomAt(c.clientWidth / 2, c.clientHeight / 2, 1.5); };
    $("zoomout").onclick = () => { const c = $("map"); zoomAt(c.clientWidth / 2, c.clientHeight / 2, 1 / 1.5); };
    $("sideaxis").onclick = () => { S.sideAxis = S.sideAxis === "n" ? "e" : "n"; $("sideaxis").textContent = S.sideAxis === "n" ? "north" : "east"; touch(); };
    $("prev").onclick = () => { S.page = Math.max(0, S.page - 1); renderTable(); };
    $("next").onclick = () => { S.page += 1; renderTable(); };
    $("filter").oninput = () => { S.page = 0; renderTable(); };
    $("sort").onchange = () => { S.page = 0; renderTable(); };
    for (const b of document.querySelectorAll("button.cmd")) b.addEventListener("click", () => issue(b.dataset.cmd));
    $("goto-pick").onclick = () => { S.pick = !S.pick; if (S.pick) S.pickWps = []; $("pickhint").hidden = !S.pick; $("goto-pick").textContent = S.pick ? "stop picking" : "pick on map"; };
    window.addEventListener("keydown", (ev) => {
      if (ev.key === "Escape" && S.pick) $("goto-pick").click();
      if (ev.key === " " && S.meta && S.meta.mode === "replay" && ev.target === document.body) { ev.preventDefault(); $("play").click(); }
    });
    $("play").onclick = () => {
      const playing = S.frame ? (S.frame.flags & FLAG_PLAYING) !== 0 : !!(S.status && S.status.replay && S.status.replay.playing);
      send({ type: "replay", op: playing ? "pause" : "play", id: `r${++S.reqId}` });
    };
    $("speed").onchange = () => send({ type: "replay", op: "speed", speed: Number($("speed").value), id: `r${++S.reqId}` });
    const scrub = $("scrub");
    const seek = (force) => {
      const r = (S.meta && S.meta.replay) || null; if (!r) return;
      const now = performance.now(); if (!force && now - S.lastSeek < 80) return; S.lastSeek = now;
      const t1 = (S.status && S.status.replay ? S.status.replay.t1 : r.t1), t0 = r.t0;
      send({ type: "replay", op: "seek", t: t0 + (Number(scrub.value) / 1000) * (t1 - t0), id: `r${++S.reqId}` });
    };
    scrub.addEventListener("input", () => { S.scrubbing = true; seek(false); });
    scrub.addEventListener("change", () => { seek(true); S.scrubbing = false; });
  }

  // ------------------------------------------------------------------ what tests and the bench read
  function pct(a, q) { if (!a.length) return null; const s = a.slice().sort((x, y) => x - y); return s[Math.min(s.length - 1, Math.floor(q * (s.length - 1) + 0.5))]; }
  window.SDConsole = {
    state: S,
    info() {
      const fr = S.frame;
      return {
        connected: S.connected, mode: S.meta ? S.meta.mode : null, n: fr ? fr.n : 0, drawn: S.drawn, onScreen: S.onScreen,
        t: fr ? fr.t : null, seq: fr ? fr.seq : null, frames: S.frames, framesDrawn: S.framesDrawn,
        known: fr ? Array.from(fr.known).reduce((a, b) => a + b, 0) : 0, lastError: S.lastError || null,
      };
    },
    positions() { const fr = S.frame; return fr ? Array.from(fr.pos) : []; },
    phases() { const fr = S.frame; return fr ? Array.from(fr.phase) : []; },
    screen() { return { x: Array.from(S.px), y: Array.from(S.py) }; },
    frameStats(from) {
      const ft = S.frameTimes.slice(from || 0), dt = S.drawTimes.slice(from || 0);
      return { count: ft.length, frame_p50: pct(ft, 0.5), frame_p95: pct(ft, 0.95), frame_max: ft.length ? Math.max(...ft) : null,
        draw_p50: pct(dt, 0.5), draw_p95: pct(dt, 0.95) };
    },
    resetTimes() { S.frameTimes.length = 0; S.drawTimes.length = 0; },
    setFlushDraw(on) { S.flushDraw = !!on; },
    geo: (n, e, d) => window.SDGeo.nedToGeodetic(n, e, d, S.meta.mission.origin),
  };

  bind();
  connect();
  setInterval(renderTable, 500);
  requestAnimationFrame(frameLoop);
})();
