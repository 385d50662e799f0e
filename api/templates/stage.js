{#- the control room's script (stage.html sets CAMERAS and HAS_BOARD); everything it fetches is on this server -#}
(function(){
  const $ = (id) => document.getElementById(id);
  const tiles = {};
  for (const t of document.querySelectorAll('.tile')) tiles[t.dataset.cam] = t;
  const role = (cid, r) => tiles[cid].querySelector('[data-role="' + r + '"]');
  const tokenBox = $('token');
  tokenBox.value = sessionStorage.getItem('stage-token') || '';
  tokenBox.addEventListener('change', () => sessionStorage.setItem('stage-token', tokenBox.value.trim()));
  window.__stage = {parts: {}, shown: {}, live3dDraws: 0, lastLive3d: null};
  for (const [cid, t] of Object.entries(tiles)){  // previews decoded and shown, per camera
    t.querySelector('img').addEventListener('load', () => { window.__stage.shown[cid] = (window.__stage.shown[cid] || 0) + 1; });
  }

  async function api(method, url, body){
    const h = {'Accept': 'application/json'};
    const tok = tokenBox.value.trim();
    if (tok) h['Authorization'] = 'Bearer ' + tok;
    if (body !== undefined) h['Content-Type'] = 'application/json';
    const r = await fetch(url, {method, headers: h, body: body === undefined ? undefined : JSON.stringify(body)});
    let data = null;
    try { data = await r.json(); } catch (e) {}
    return {ok: r.ok, status: r.status, data};
  }
  function say(el, text, kind){ el.textContent = text; el.className = 'msg' + (kind ? ' ' + kind : ''); }
  function detail(res){
    const d = res.data && res.data.detail;
    // a validation error (422) is a list of {loc, msg}: said as "field: message", never as raw JSON
    const text = typeof d === 'string' ? d : Array.isArray(d) ?
      d.map((e) => ((e.loc || []).filter((x) => x !== 'body').join('.') || 'request') + ': ' + e.msg).join('; ') : JSON.stringify(d);
    if (res.status === 401) return 'refused (401): enter the API token above. ' + text;
    return '(' + res.status + ') ' + text;
  }
  const fmt = (v, n) => (v === null || v === undefined) ? '–' : Number(v).toFixed(n === undefined ? 1 : n);

  // ---- previews: one multipart stream for every camera, parsed here (X-Camera names each part)
  const enc = new TextEncoder();
  const HEAD_END = enc.encode('\r\n\r\n');
  function find(buf, seq, from){
    outer: for (let i = from; i <= buf.length - seq.length; i++){
      for (let j = 0; j < seq.length; j++) if (buf[i + j] !== seq[j]) continue outer;
      return i;
    }
    return -1;
  }
  let streamAbort = null;
  const lastPicture = {};  // camera -> when its last preview arrived (performance.now())
  const pageOpened = performance.now();
  async function previews(){
    if (streamAbort) streamAbort.abort();
    const ctl = new AbortController(); streamAbort = ctl;
    const h = {}; const tok = tokenBox.value.trim(); if (tok) h['Authorization'] = 'Bearer ' + tok;
    try {
      const r = await fetch('/stage/previews.mjpg?mask=' + ($('mask').checked ? 'true' : 'false'), {headers: h, signal: ctl.signal});
      if (!r.ok) throw new Error('previews: ' + r.status);
      const reader = r.body.getReader();
      let buf = new Uint8Array(0);
      for (;;){
        const {value, done} = await reader.read();
        if (done) break;
        const nb = new Uint8Array(buf.length + value.length); nb.set(buf); nb.set(value, buf.length); buf = nb;
        for (;;){
          const he = find(buf, HEAD_END, 0);
          if (he < 0) break;
          const head = new TextDecoder().decode(buf.subarray(0, he));
          const len = parseInt((/Content-Length:\s*(\d+)/i.exec(head) || [])[1], 10);
          const cam = ((/X-Camera:\s*(\S+)/i.exec(head) || [])[1]);
          if (!(len >= 0) || buf.length < he + 4 + len + 2) break;
          const jpg = buf.slice(he + 4, he + 4 + len);
          buf = buf.slice(he + 4 + len + 2);
          const img = tiles[cam] && tiles[cam].querySelector('img');
          if (!img) continue;
          const old = img.src;
          img.src = URL.createObjectURL(new Blob([jpg], {type: 'image/jpeg'}));
          if (old.startsWith('blob:')) setTimeout(() => URL.revokeObjectURL(old), 1000);
          window.__stage.parts[cam] = (window.__stage.parts[cam] || 0) + 1;
          lastPicture[cam] = performance.now();
        }
      }
    } catch (e) { if (ctl.signal.aborted) return; }
    if (!ctl.signal.aborted) setTimeout(previews, 1000);  // the server went away: try again
  }
  $('mask').addEventListener('change', previews);

  // ---- figures
  let recState = 'idle';
  let previewPeriod = 0.2;  // s between a camera's previews (the server's --preview-fps)
  function showCamera(c, board){
    const t = tiles[c.id]; if (!t) return;
    const gone = c.state === 'disconnected' || c.state === 'failed';
    t.classList.toggle('gone', gone);
    // a picture that no longer changes is greyed and says so: a frozen frame must not pass for a live one
    const age = (performance.now() - (lastPicture[c.id] || pageOpened)) / 1000;
    const stale = gone || age > Math.max(3, 3 * previewPeriod);
    t.classList.toggle('stale', stale);
    role(c.id, 'stale').hidden = !stale;
    role(c.id, 'stale').textContent = !lastPicture[c.id] ? 'no picture yet' :
      gone ? 'last picture before it went away' : 'no new picture for ' + age.toFixed(0) + ' s';
    t.classList.toggle('recording', recState === 'recording' && !gone);
    role(c.id, 'state').textContent = gone ? (c.state === 'failed' ? 'failed to open' : 'DISCONNECTED') : c.state;
    role(c.id, 'error').textContent = c.error ? ' ' + c.error : '';
    role(c.id, 'fps').textContent = fmt(c.fps);
    role(c.id, 'dropped').textContent = c.dropped + (c.dropped_recent ? ' (' + c.dropped_recent + ' in the last ' + c.dropped_recent_s + ' s)' : '');
    role(c.id, 'dropped').className = c.dropped_recent ? 'warn' : '';
    // how late this camera's frames are against the others' in the last frame sets; amber only for what was
    // lost: sets without it (it is not in their 3-D), frames the device dropped just now
    const sy = c.sync || {}; const syEl = role(c.id, 'sync');
    const off = sy.offset_ms;
    const miss = !gone && sy.missing ? 'MISSING from ' + sy.missing + ' of the last ' + sy.sets + ' frame sets; ' : '';
    syEl.textContent = gone || !sy.sets ? 'sync –' : miss + (off === null || off === undefined ? 'sync: in no set with another camera' :
      'sync: ' + (Math.abs(off) < 0.05 ? 'on time' : fmt(Math.abs(off), 1) + ' ms ' + (off > 0 ? 'late' : 'early')));
    syEl.title = sy.sets ? 'against the median of the other cameras, over its last ' + (sy.sets - sy.missing) + ' frame sets' : '';
    syEl.className = miss ? 'warn' : 'muted';
    role(c.id, 'take').textContent = (c.take_missing !== undefined) ?
      '· take: missing ' + c.take_missing + (c.take_queue_drops ? ' + ' + c.take_queue_drops + ' queue' : '') : '';
    const im = c.image;  // the picture's own exposure and focus figures (api.control.image_figures)
    const imEl = role(c.id, 'image');
    imEl.textContent = !im ? 'level – · clipped – · sharpness –' : (im.exposure ? im.exposure.toUpperCase() + ': ' : '') +
      'level ' + fmt(im.level, 0) + ' · clipped ' + fmt(im.clipped_pct, 1) + ' % · sharpness ' + fmt(im.sharpness, 0);
    imEl.className = im && im.exposure ? 'warn' : 'muted';
    const ex = [];
    if (c.exposure_ms !== null) ex.push('exposure ' + fmt(c.exposure_ms, 2) + ' ms'); else ex.push('exposure –');
    ex.push(c.gain !== null && c.gain !== undefined ? 'gain ' + fmt(c.gain) + (c.gain_unit === 'ISO' ? ' ISO' : '') : 'gain –');
    role(c.id, 'exp').textContent = ex.join(' · ');
    role(c.id, 'bus').textContent = c.bus === null ? '· ' + fmt(c.stream_mbps, 0) + ' Mbit/s, not on a USB bus' :
      '· USB bus ' + c.bus + ': ' + fmt(c.bus_need_mbps, 0) + '/' + fmt(c.bus_budget_mbps, 0) + ' Mbit/s' + (c.oversubscribed ? ' OVERSUBSCRIBED' : '');
  }
  function relocked(sync){  // cameras whose frames left their sync chain (stage info's warning)
    const cams = Object.entries(sync.cameras || {}).filter(([, c]) => c.relocks > 0);
    return cams.length ? '; sync re-locked (sets before may pair instants): ' +
      cams.map(([id, c]) => id + ' before set ' + (c.last_relock_set ?? c.first_relock_set)).join(', ') : '';
  }
  window.__stage.relocked = relocked;  // the page's own wording, read by its browser test
  function takeProblems(res){  // what makes a finished take worth a second look, first in its line (amber)
    const s = res.sync || {}; const out = [];
    const gone = Object.keys(res.disconnected || {});
    if (gone.length) out.push(gone.join(', ') + ' disconnected');
    // the first and last sets may miss a camera (cut by start and stop): more than those is a problem
    const incomplete = res.sets - (s.sets_complete === undefined ? res.sets : s.sets_complete);
    if (incomplete > 2) out.push(incomplete + ' of ' + res.sets + ' frame sets incomplete');
    if (Object.values(s.cameras || {}).some((c) => c.relocks > 0)) out.push('sync re-locked');
    return out;
  }
  window.__stage.takeProblems = takeProblems;
  function showRecording(rec){
    recState = rec.state || 'idle';
    // stop only what runs; record stays pressable (a second take is refused by the server, which says why,
    // as it does for another browser's press)
    $('stop').disabled = recState !== 'recording';
    $('recorder').classList.toggle('recording', recState === 'recording');  // seen from across the room
    $('rec-state').textContent = recState + (rec.take ? ' (' + rec.take + ')' : '');
    $('rec-frames').textContent = rec.frames_written || 0;
    $('rec-drops').textContent = rec.drops || 0;
    $('rec-timer').textContent = fmt(rec.elapsed_s || 0);
    if (rec.result){
      const s = rec.result.sync || {};
      $('rec-state').dataset.sets = rec.result.sets;
      $('rec-state').dataset.spreadMedianMs = s.spread_median_ms;
      $('rec-state').dataset.setsComplete = s.sets_complete;
      if (recState === 'done' && lastShown !== rec.take){
        lastShown = rec.take;
        const problems = takeProblems(rec.result);
        say($('rec-msg'), (problems.length ? 'take ' + rec.take + ' has problems: ' + problems.join('; ') + '. ' : 'take ' + rec.take + ': ') +
            rec.result.sets + ' frame sets (' + s.sets_complete + ' complete), sync spread median ' +
            fmt(s.spread_median_ms, 2) + ' ms, max ' + fmt(s.spread_max_ms, 2) + ' ms' + relocked(s) +
            (Object.keys(rec.result.disconnected || {}).length ? '; disconnected: ' + Object.keys(rec.result.disconnected).join(', ') : ''),
            problems.length ? 'warn' : 'good');
        takes();
      }
    }
    if (recState === 'failed') say($('rec-msg'), 'take ' + rec.take + ' failed: ' + rec.error, 'bad');
  }
  let lastShown = null, answered = null;
  async function figures(){
    try {
      const r = await api('GET', '/stage');
      if (r.ok){
        const f = r.data;
        const d = f.disk || {};
        $('disk-free').textContent = d.free_bytes ? (d.free_bytes / 1e9).toFixed(1) + ' GB' : '–';
        $('minutes-left').textContent = fmt(d.minutes_left, 0);
        say($('disk-msg'), d.message || '', d.level === 'full' ? 'bad' : d.level === 'low' ? 'warn' : '');
        const s = f.sync_spread_ms || {};
        // against the tolerance frame sets are grouped within (half a frame period unless the rig sets it)
        $('spread').textContent = (s.median === null ? '–' : fmt(s.median, 2) + ' ms median, ' + fmt(s.max, 2) + ' ms max') +
          (f.tolerance_ms ? ' (sets group within ' + fmt(f.tolerance_ms, 1) + ' ms)' : '');
        const l = (f.previews || {}).latency_ms || {};
        $('latency').textContent = l.p50 === null || l.p50 === undefined ? '–' : fmt(l.p50, 0) + ' / ' + fmt(l.p99, 0) + ' ms';
        const tc = f.take_calibration || {};  // what a take recorded now stores, or why nothing
        say($('take-cal'), tc.message || '', tc.calibrated ? '' : 'bad');
        if ((f.previews || {}).fps) previewPeriod = 1 / f.previews.fps;
        showRecording(f.recording || {});
        for (const c of f.cameras) showCamera(c);
        // the cameras not running, named in one line at the top: a red tile may be scrolled out of view
        const down = f.cameras.filter((c) => c.state === 'disconnected' || c.state === 'failed');
        $('cams-msg').textContent = down.length ? down.length + ' of ' + f.cameras.length + ' cameras not running: ' +
          down.map((c) => c.id + ' ' + (c.state === 'failed' ? 'failed to open' : 'disconnected') + (c.error ? ' (' + c.error + ')' : '')).join('; ') : '';
        answered = new Date();
        $('conn-msg').textContent = '';
      } else throw new Error(String(r.status));
    } catch (e) {  // the figures stop: said, with the time of the last ones, never left to pass for live
      $('conn-msg').textContent = 'the server does not answer (' + (e.message || e) + '): the figures and pictures are from ' +
        (answered ? answered.toLocaleTimeString() : 'nothing yet') + '; trying again';
    }
    setTimeout(figures, 700);
  }

  // ---- record / stop
  function defaultName(){
    const d = new Date(); const p = (n) => String(n).padStart(2, '0');
    return 'take-' + d.getFullYear() + p(d.getMonth() + 1) + p(d.getDate()) + '-' + p(d.getHours()) + p(d.getMinutes()) + p(d.getSeconds());
  }
  $('take-name').value = defaultName();
  $('record').addEventListener('click', async () => {
    const name = $('take-name');
    if (!name.checkValidity()){  // said here, before asking the server
      say($('rec-msg'), 'not recording: a take name is letters, digits, "_", "." and "-", starting with a letter or digit', 'bad');
      name.focus(); return;
    }
    const body = {take: name.value.trim()};
    const secs = parseFloat($('take-seconds').value);
    if (secs > 0) body.duration_s = secs;
    const r = await api('POST', '/stage/record', body);
    if (r.ok){ say($('rec-msg'), 'recording ' + body.take, ''); lastShown = null; $('take-name').value = defaultName(); }
    else say($('rec-msg'), 'not recording: ' + detail(r), 'bad');
  });
  $('stop').addEventListener('click', async () => {
    const r = await api('POST', '/stage/stop');
    if (!r.ok) say($('rec-msg'), 'stop: ' + detail(r), 'bad');
  });

  // ---- board session
  function drawCoverage(canvas, grid){
    const ctx = canvas.getContext('2d'); const rows = grid.length, cols = grid[0].length;
    const w = canvas.width / cols, h = canvas.height / rows;
    let mx = 1; for (const r of grid) for (const v of r) mx = Math.max(mx, v);
    for (let y = 0; y < rows; y++) for (let x = 0; x < cols; x++){
      const v = grid[y][x] / mx;
      ctx.fillStyle = grid[y][x] ? 'rgba(76,175,80,' + (0.3 + 0.7 * v) + ')' : 'rgba(183,28,28,0.55)';
      ctx.fillRect(x * w, y * h, w - 1, h - 1);
    }
  }
  function showPairs(st){  // shared views per camera pair, built as elements (camera ids are text, never markup)
    const cell = (tag, text) => { const e = document.createElement(tag); e.textContent = text; return e; };
    const table = document.createElement('table');
    const head = table.insertRow(); head.appendChild(cell('th', ''));
    for (const c of st.cameras) head.appendChild(cell('th', c));
    st.cameras.forEach((a, i) => {
      const tr = table.insertRow(); tr.appendChild(cell('th', a));
      st.cameras.forEach((b, j) => {
        if (i === j){ tr.appendChild(cell('td', '·')); return; }
        const n = st.shared[i][j]; const td = cell('td', n);
        td.className = n >= st.min_shared ? 'link' : n ? 'some' : 'none';
        td.title = a + ' and ' + b + ': ' + n + ' shared views' + (n >= st.min_shared ? ' (linked)' : '');
        tr.appendChild(td);
      });
    });
    const note = cell('p', 'shared views per camera pair (green: a link for the bundle adjustment)'); note.className = 'muted';
    $('pairs').replaceChildren(note, table);
  }
  let boardPoll = null, calibJob = null;
  async function board(){
    const r = await api('GET', '/stage/board');
    if (r.ok && r.data.cameras){
      const st = r.data;
      for (const c of st.cameras){
        const t = tiles[c]; if (!t) continue;
        const m = t.querySelector('.meter'); m.hidden = false;
        m.querySelector('progress').max = st.min_views; m.querySelector('progress').value = Math.min(st.views[c], st.min_views);
        role(c, 'views').textContent = st.views[c] + (st.detected[c] ? ' · board seen' : '');
        const cv = t.querySelector('canvas.coverage'); cv.hidden = false; drawCoverage(cv, st.coverage[c]);
      }
      showPairs(st);
      say($('board-msg'), st.message, st.enough ? 'good' : '');
      $('board-msg').dataset.enough = st.enough;
      $('calibrate').disabled = !(st.running && st.take);
      if (!st.running && !calibJob) { boardPoll = null; return; }
    }
    if (!calibJob) boardPoll = setTimeout(board, 800);
  }
  function showReport(job, rep){
    $('calib-report').hidden = false;
    $('calib-state').textContent = 'calibration job ' + job.id.slice(0, 8) + ': ' + job.state + (job.error ? ' — ' + job.error : '');
    if (!rep) return;
    $('calib-summary').textContent = rep.summary;
    const ev = rep.evaluation || {}; const ho = (ev.held_out || {}).per_camera || {}; const af = (ev.all_frames || {}).per_camera || {};
    const tb = $('calib-errors').querySelector('tbody'); tb.innerHTML = '';
    for (const name of Object.keys(af).length ? Object.keys(af) : Object.keys(ho)){
      const tr = document.createElement('tr');
      for (const v of [name, ho[name] ? fmt(ho[name].rms, 3) : '–', af[name] ? fmt(af[name].rms, 3) : '–', af[name] ? af[name].views : '–']){
        const td = document.createElement('td'); td.textContent = v; tr.appendChild(td);
      }
      tb.appendChild(tr);
    }
    const ul = $('calib-warnings'); ul.innerHTML = '';
    for (const w of rep.warnings || []){ const li = document.createElement('li'); li.textContent = w; ul.appendChild(li); }
    $('calib-nwarn').textContent = (rep.warnings || []).length;
    $('calib-report').dataset.done = 'true';
  }
  async function followCalibration(){
    const r = await api('GET', '/jobs/' + calibJob);
    if (r.ok){
      const j = r.data;
      showReport(j, null);
      if (j.state === 'done'){
        const rep = await api('GET', '/jobs/' + calibJob + '/results/report.json');
        showReport(j, rep.ok ? rep.data : null);
        if (!rep.ok || !rep.data) $('calib-summary').textContent = 'the report could not be read: ' + (rep.ok ? 'not JSON' : detail(rep));
        return;
      }
      if (j.state === 'failed' || j.state === 'cancelled') return;
    }
    setTimeout(followCalibration, 1000);
  }
  if (HAS_BOARD){
    $('board-start').addEventListener('click', async () => {
      const r = await api('POST', '/stage/board/start', {min_views: parseInt($('min-views').value, 10) || 8,
                                                          min_shared: parseInt($('min-shared').value, 10) || 3});
      if (!r.ok){ say($('board-msg'), 'board session: ' + detail(r), 'bad'); return; }
      calibJob = null; $('calib-report').hidden = true;
      if (!boardPoll) board();
    });
    $('calibrate').addEventListener('click', async () => {
      const folds = parseInt($('holdout').value, 10);
      const r = await api('POST', '/stage/board/calibrate', {holdout: folds >= 0 ? folds : 5, step: parseInt($('cal-step').value, 10) || 1});
      if (!r.ok){ say($('board-msg'), 'calibrate: ' + detail(r), 'bad'); return; }
      calibJob = r.data.job; $('calibrate').disabled = true;
      say($('board-msg'), 'calibrating take ' + r.data.take + ' (job ' + calibJob.slice(0, 8) + ')', '');
      board(); followCalibration();
    });
    board();
  }

  // ---- live 3-D: surface voxels of the coarse hull and the spine, turning slowly
  const cv3 = $('live3d'); const ctx3 = cv3.getContext('2d'); let live = null; let idleText = null;
  function draw3d(){
    const W = cv3.width, H = cv3.height;
    if (!(live && live.state === 'ok')){
      // nothing turns: the message is drawn when it changes, not on every animation frame
      const text = live ? (live.message || live.state) : 'waiting for the first frame set';
      if (text !== idleText){
        idleText = text; ctx3.fillStyle = '#102027'; ctx3.fillRect(0, 0, W, H);
        ctx3.fillStyle = '#cfd8dc'; ctx3.font = '14px sans-serif'; ctx3.fillText(text, 16, 28);
      }
      setTimeout(() => requestAnimationFrame(draw3d), 250);
      return;
    }
    idleText = null; ctx3.fillStyle = '#102027'; ctx3.fillRect(0, 0, W, H);
    // framed on the capture volume, drawn as a box: where the subject stands in it is what the view is for
    const [vlo, vhi] = live.bounds;
    const c = [0, 1, 2].map((i) => (vlo[i] + vhi[i]) / 2);
    const ext = Math.max(vhi[0] - vlo[0], vhi[1] - vlo[1], vhi[2] - vlo[2]) * 1.25;
    const a = performance.now() / 4000, ca = Math.cos(a), sa = Math.sin(a), el = 0.45, ce = Math.cos(el), se = Math.sin(el);
    const s = 0.8 * Math.min(W, H) / ext;
    const proj = (p) => { const x = p[0] - c[0], y = p[1] - c[1], z = p[2] - c[2];
      const u = ca * x - sa * y, v = sa * x + ca * y; return [W / 2 + s * u, H / 2 - s * (ce * z - se * v), ce * v + se * z]; };
    const corner = (i) => [i & 1 ? vhi[0] : vlo[0], i & 2 ? vhi[1] : vlo[1], i & 4 ? vhi[2] : vlo[2]];
    for (const floor of [false, true]){  // the volume's 12 edges; the 4 of its floor brighter
      ctx3.strokeStyle = floor ? '#b0bec5' : '#546e7a'; ctx3.lineWidth = floor ? 1.5 : 1; ctx3.beginPath();
      for (let i = 0; i < 8; i++) for (const b of [1, 2, 4]){
        const j = i | b; if (j === i || (floor !== !((i | j) & 4))) continue;
        const P = proj(corner(i)), Q = proj(corner(j)); ctx3.moveTo(P[0], P[1]); ctx3.lineTo(Q[0], Q[1]);
      }
      ctx3.stroke();
    }
    const pts = live.points.map(proj).sort((p, q) => q[2] - p[2]);
    const r = Math.max(1.5, s * live.voxel * 0.6);
    for (const p of pts){ const k = Math.round(120 + 100 * Math.max(-1, Math.min(1, -p[2] / ext * 2)));
      ctx3.fillStyle = 'rgb(' + k + ',' + Math.round(k * 0.8) + ',90)'; ctx3.fillRect(p[0] - r / 2, p[1] - r / 2, r, r); }
    ctx3.strokeStyle = '#4fc3f7'; ctx3.lineWidth = 3; ctx3.beginPath();
    for (const [p, q] of live.segments){ const P = proj(p), Q = proj(q); ctx3.moveTo(P[0], P[1]); ctx3.lineTo(Q[0], Q[1]); }
    ctx3.stroke();
    window.__stage.live3dDraws++;
    requestAnimationFrame(draw3d);
  }
  let seen3d = [];
  async function poll3d(){
    try {
      const r = await api('GET', '/stage/live3d');
      if (r.ok){
        live = r.data; window.__stage.lastLive3d = {state: live.state, updates: live.updates, points: (live.points || []).length, calibration: live.calibration,
                                                     segments: (live.segments || []).length};
        const now = performance.now();
        if (live.updates !== undefined && (!seen3d.length || seen3d[seen3d.length - 1][1] !== live.updates)) seen3d.push([now, live.updates]);
        seen3d = seen3d.filter((x) => x[0] > now - 5000);
        const rate = seen3d.length > 1 ? (seen3d.length - 1) / ((seen3d[seen3d.length - 1][0] - seen3d[0][0]) / 1000) : 0;
        // the subject where the view cannot see it whole: one line, in amber, above the figures
        const edges = live.state === 'ok' ? (live.edges || []) : [];
        say($('live3d-edge'), live.state !== 'ok' ? '' : live.occupied === 0 ? 'nothing in the capture volume' :
            edges.length ? 'the subject reaches the capture volume\'s ' + edges.map((e) => e === 'z max' ? 'top (z max)' : e).join(', ') + ' side' + (edges.length > 1 ? 's' : '') +
            ': what is outside the volume is not reconstructed' : '', 'warn');
        $('live3d-edge').dataset.edges = edges.join(',');
        $('live3d-box').hidden = live.state !== 'ok';
        // in the rig's words: what it shows, how old that is, how often it is renewed
        $('live3d-info').textContent = live.state === 'ok' ? ('frame set ' + live.set +
          (live.age_s !== null && live.age_s !== undefined ? ', ' + fmt(live.age_s, 1) + ' s ago' : '') + ': ' +
          live.occupied + ' voxels (' + fmt(live.voxel, 0) + ' mm cubes) in the hull' +
          (live.segments.length ? ', a skeleton of ' + live.segments.length + ' segments' : '') +
          '; the view is renewed ' + fmt(rate, 1) + ' times a second, each taking ' + fmt(live.compute_ms / 1000, 2) + ' s to build' +
          (live.calibration ? '; ' + live.calibration : '') +
          ((live.uncalibrated || []).length ? '; carved without ' + live.uncalibrated.join(', ') + ' (not in the calibration)' : '')) :
          (live.message || live.state);
      }
    } catch (e) {}
    setTimeout(poll3d, 250);
  }

  // ---- takes
  async function takes(){
    const r = await api('GET', '/takes');
    if (!r.ok) return;
    const tb = $('take-list'); tb.innerHTML = '';
    const newest = r.data.slice().sort((a, b) => b.modified - a.modified).slice(0, 20);
    for (const t of newest){
      const tr = document.createElement('tr'); tr.dataset.take = t.id;
      const a = document.createElement('a'); a.href = '/ui/takes/' + encodeURIComponent(t.id); a.textContent = t.id;
      const td0 = document.createElement('td'); td0.appendChild(a);
      const td1 = document.createElement('td'); td1.textContent = t.frames === undefined ? '–' : t.frames;
      const td2 = document.createElement('td'); td2.textContent = (t.size_bytes / 1e6).toFixed(1) + ' MB';
      const td3 = document.createElement('td'); const b = document.createElement('button'); b.textContent = 'process';
      b.addEventListener('click', async () => {  // the job is followed in its row: the control room stays open
        const j = await api('POST', '/jobs', {take: t.id});
        if (!j.ok){ say($('rec-msg'), 'process: ' + detail(j), 'bad'); return; }
        lastJobs[t.id] = j.data; showJob(tr, j.data);
        say($('rec-msg'), 'processing take ' + t.id + ': job ' + j.data.id.slice(0, 8) + ' (followed in the take list)', '');
      });
      td3.appendChild(b);
      const td4 = document.createElement('td'); td4.className = 'muted';
      const td5 = document.createElement('td'); td5.textContent = '…';
      const td6 = document.createElement('td'); td6.className = 'job';
      tr.append(td0, td1, td2, td4, td5, td3, td6); tb.appendChild(tr);
      showJob(tr, lastJobs[t.id]);
      api('GET', '/takes/' + encodeURIComponent(t.id)).then((i) => {  // stage info's figures
        if (!i.ok) return;
        const sync = i.data.sync || {};
        td1.textContent = i.data.frames;
        // a take without a calibration cannot be processed (its job would fail at once): said here, not later
        td5.textContent = i.data.calibration ? 'yes' : 'none: cannot be processed';
        td5.className = i.data.calibration ? '' : 'err';
        b.disabled = !i.data.calibration;
        if (!i.data.calibration) b.title = 'the take has no calibration';
        if (!i.data.calibration && i.data.complete !== false) offerCalibration(tr, t.id, td5);
        showJob(tr, lastJobs[t.id]);  // (a board take's calibration cell reads by its job)
        td4.textContent = (sync.sets_complete !== undefined ? sync.sets_complete + ' complete sets, ' : '') +
          (sync.spread_median_ms !== undefined ? 'sync spread median ' + fmt(sync.spread_median_ms, 2) + ' ms' : '') +
          relocked(sync) + (i.data.complete === false ? ' (being written)' : '');
      });
    }
  }
  // ---- a take recorded without a calibration can be given the newest one the server has (PUT /takes/{id}/calibration)
  async function offerCalibration(tr, take, td){
    const r = await api('GET', '/calibrations');
    if (!r.ok || !r.data.length || td.textContent.startsWith('none: a board take')) return;
    const newest = r.data[r.data.length - 1];  // (listed oldest first)
    const b = document.createElement('button'); b.className = 'use-cal';
    b.textContent = 'use calibration ' + newest.id.slice(0, 8);
    b.title = 'make calibration ' + newest.id + ' (the newest on this server) this take\'s, so it can be processed';
    b.addEventListener('click', async () => {
      const p = await api('PUT', '/takes/' + encodeURIComponent(take) + '/calibration', {calibration: newest.id});
      if (!p.ok){ say($('rec-msg'), 'take ' + take + ' not calibrated: ' + detail(p), 'bad'); return; }
      say($('rec-msg'), 'take ' + take + ' now has calibration ' + newest.id.slice(0, 8), 'good');
      takes();
    });
    td.append(' ', b);
  }

  // ---- each listed take's newest job: state, progress, report link, a failure's first line
  let lastJobs = {};
  function showJob(tr, j){
    const td = tr.querySelector('td.job'); td.replaceChildren();
    if (!j){ td.textContent = '–'; return; }
    const a = document.createElement('a'); a.href = '/ui/jobs/' + j.id; a.textContent = j.kind + ' ' + j.id.slice(0, 8);
    const active = j.state === 'queued' || j.state === 'running';
    const st = document.createElement('span'); st.className = 'state state-' + j.state;
    // the step at work: the first entry not finished, in the order the steps run (the progress keeps it), named
    // with its step when it is a part of one ("step surface: box 2/4")
    const at = active ? Object.entries(j.progress || {}).find(([, p]) => p.done < p.total) : null;
    const part = at && at[1].step && at[1].step !== at[0] ? at[1].step + ': ' : '';
    st.textContent = ' ' + j.state + (active ? ' ' + j.done + '/' + j.total : '') +
      (at ? ' · step ' + part + at[0] + ' ' + at[1].done + '/' + at[1].total : '');
    td.append(a, st);
    if (j.state === 'done' && j.kind === 'process'){
      const r = document.createElement('a'); r.href = '/ui/jobs/' + j.id + '/report'; r.textContent = 'report';
      td.append(' · ', r);
    }
    // a board take (its newest job calibrates from it) is not a subject take: no alarm for its missing calibration
    const cal = tr.cells[4];
    if (j.kind === 'calibrate' && cal && cal.textContent.startsWith('none')){ cal.textContent = 'none: a board take'; cal.className = 'muted'; }
    if (j.state === 'failed' && j.error){
      const e = document.createElement('div'); e.className = 'err'; e.textContent = j.error.split('\n')[0]; td.append(e);
    }
  }
  async function takeJobs(){
    try {
      const r = await api('GET', '/jobs?limit=200');
      if (r.ok){
        const newest = {};
        for (const j of r.data) if (!(j.take in newest)) newest[j.take] = j;  // newest first
        lastJobs = newest;
        for (const tr of $('take-list').rows) showJob(tr, newest[tr.dataset.take]);
      }
    } catch (e) {}
    setTimeout(takeJobs, 2000);
  }
  previews(); figures(); poll3d(); takes(); takeJobs(); requestAnimationFrame(draw3d);
})();
