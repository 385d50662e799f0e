{#- follows one job: polls /jobs/{id} every second until it is finished, and for a processing job its results'
    listing (/jobs/{id}/results/): links to what it has written so far, never to what it has not, every frame of
    its per-frame folders in a collapsed list; a listing that cannot be read is said, and asked again, a finished
    job's until it answers; a calibration job's page is loaded again when the job ends, with what it made
    (JOB_ID, INITIAL_STATE, RESULT_STEPS, FRAME_LINKS: set by the page; pages.py _frame_lists, _unwritten,
    _calibration_links say it alike) -#}
(function(){
  const TERMINAL = ["done", "failed", "cancelled"];
  function renderFrames(l){
    const div = document.getElementById('frames');
    for (const [key, url, text] of FRAME_LINKS){
      const frames = l[key] || [];
      let d = div.querySelector('details[data-key="' + key + '"]');
      if (!frames.length){ if (d) d.remove(); continue; }
      if (!d){  // (a list the user opened stays open as the job runs)
        d = document.createElement('details'); d.dataset.key = key;
        d.appendChild(document.createElement('summary'));
        const p = document.createElement('p'); p.className = 'frames'; d.appendChild(p);
      }
      div.appendChild(d);  // (in FRAME_LINKS' order)
      d.querySelector('summary').textContent = text + ' (' + frames.length + ' frame set' + (frames.length === 1 ? '' : 's') + ')';
      if (d.dataset.frames === frames.join(',')) continue;
      d.dataset.frames = frames.join(',');
      const p = d.querySelector('p.frames'); p.replaceChildren();
      for (const k of frames){
        const a = document.createElement('a'); a.textContent = String(k); a.title = 'frame set ' + k;
        a.href = l[url].replace('{index:06d}', String(k).padStart(6, '0'));
        p.appendChild(a); p.appendChild(document.createTextNode(' '));
      }
    }
  }
  function renderResults(j, l){
    const span = document.getElementById('results');
    if (!span) return;
    span.replaceChildren();
    for (const [text, url] of Object.entries(l.links || {})){
      const a = document.createElement('a'); a.href = url; a.textContent = text;
      span.appendChild(document.createTextNode(' · ')); span.appendChild(a);
    }
    renderFrames(l);
    const steps = j.steps.filter(s => RESULT_STEPS.includes(s) && !(l.written_by || []).includes(s));
    const p = document.getElementById('unwritten');
    p.textContent = '';
    if ((j.state === 'failed' || j.state === 'cancelled') && steps.length){
      const named = steps.length === 1 ? steps[0] : steps.slice(0, -1).join(', ') + ' and ' + steps[steps.length - 1];
      p.textContent = 'The job ' + (j.state === 'failed' ? 'failed' : 'was cancelled') + ': the ' + named + ' step'
        + (steps.length > 1 ? 's' : '') + ' wrote nothing.';
    }
    p.hidden = !p.textContent;
  }
  function render(j){
    const st = document.getElementById('state');
    st.textContent = j.state + (j.cancel_requested && !TERMINAL.includes(j.state) ? ' (cancel requested)' : '');
    st.className = 'state state-' + j.state;
    const box = document.getElementById('cancel-box');
    if (box) box.hidden = TERMINAL.includes(j.state) || !!j.cancel_requested;
    const all = document.getElementById('bar-all');
    all.max = Math.max(j.total, 1); all.value = Math.min(j.done, all.max);
    document.getElementById('count-all').textContent = j.done + '/' + j.total;
    const tbody = document.getElementById('steps');
    for (const [step, p] of Object.entries(j.progress || {})){
      let tr = tbody.querySelector('tr[data-step="' + CSS.escape(step) + '"]');
      if (!tr){
        tr = document.createElement('tr'); tr.dataset.step = step;
        const td0 = document.createElement('td'); td0.textContent = step;
        const td1 = document.createElement('td'); const bar = document.createElement('progress');
        const sp = document.createElement('span'); sp.className = 'count';
        td1.appendChild(bar); td1.appendChild(document.createTextNode(' ')); td1.appendChild(sp);
        tr.appendChild(td0); tr.appendChild(td1); tbody.appendChild(tr);
      }
      const bar = tr.querySelector('progress');
      bar.max = Math.max(p.total, 1); bar.value = Math.min(p.done, bar.max);
      tr.querySelector('.count').textContent = p.done + '/' + p.total;
    }
    document.getElementById('attempts').textContent = j.attempts;
    for (const k of ['started', 'finished'])
      if (j[k]) document.getElementById(k).textContent = new Date(j[k] * 1000).toISOString().slice(0, 19).replace('T', ' ') + ' UTC';
    const err = document.getElementById('error');
    err.textContent = j.error || '';
    if (j.state === 'done' && j.kind === 'process') document.getElementById('report').hidden = false;
    const warned = j.warnings || [];  // what the job warned of, in every state (a failed job's before it stopped)
    const ul = document.getElementById('warning-list'); ul.replaceChildren();
    for (const w of warned){ const li = document.createElement('li'); li.textContent = w; ul.appendChild(li); }
    document.getElementById('nwarn').textContent = warned.length;
    document.getElementById('warnings').hidden = !warned.length;
    return !TERMINAL.includes(j.state);
  }
  async function listed(j){
    // (asked after the status: a job just finished has all its files listed); false when it could not be read
    let l = null, why = 'no answer';
    try {
      const r = await fetch('/jobs/' + JOB_ID + '/results/', {headers: {'Accept': 'application/json'}});
      if (r.ok) l = await r.json(); else why = 'HTTP ' + r.status;
    } catch (e) {}
    if (l) renderResults(j, l);
    const p = document.getElementById('results-error');
    p.textContent = l ? '' : 'The list of results could not be read (' + why + '): the links above may be out of'
      + ' date; asking again.';
    p.hidden = !!l;
    return !!l;
  }
  async function poll(){
    let again = true;
    try {
      const r = await fetch('/jobs/' + JOB_ID, {headers: {'Accept': 'application/json'}});
      if (r.ok){
        const j = await r.json();
        const ok = j.kind !== 'process' || await listed(j);
        // (the state last: a page that reads "done" has its results' links, or says they may be out of date and
        // asks again until the listing answers)
        again = render(j) || !ok;
        // (a calibration job's page shows what the job made as the server finds it: loaded again once it ends)
        if (!again && j.kind === 'calibrate') location.reload();
      }
    } catch (e) {}
    if (again) setTimeout(poll, 1000);
  }
  const cancel = document.getElementById('cancel');
  if (cancel){  // the token the control room keeps for this tab, else typed here
    const tok = document.getElementById('token');
    tok.value = sessionStorage.getItem('stage-token') || '';
    tok.addEventListener('change', () => sessionStorage.setItem('stage-token', tok.value.trim()));
    cancel.addEventListener('click', async () => {
      const h = {'Accept': 'application/json'}; if (tok.value.trim()) h['Authorization'] = 'Bearer ' + tok.value.trim();
      const r = await fetch('/jobs/' + JOB_ID + '/cancel', {method: 'POST', headers: h});
      let d = null; try { d = await r.json(); } catch (e) {}
      const msg = document.getElementById('cancel-msg');
      if (r.ok){ msg.textContent = ''; render(d); return; }
      const why = d && typeof d.detail === 'string' ? d.detail : String(r.status);
      msg.textContent = 'not cancelled (' + r.status + '): ' + (r.status === 401 || r.status === 403 ? 'enter the API token. ' : '') + why;
    });
  }
  if (!TERMINAL.includes(INITIAL_STATE)) setTimeout(poll, 1000);
})();
