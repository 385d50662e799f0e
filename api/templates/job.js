{#- follows one job: polls /jobs/{id} every second until it is finished, and for a processing job its results'
    listing (/jobs/{id}/results/): links to what it has written so far, never to what it has not, every frame of
    its per-frame folders in a collapsed list; a listing that cannot be read is said, and asked again, a finished
    job's until it answers; a calibration job's page is loaded again when the job ends, with what it made
    (JOB_ID, INITIAL_STATE, RESULT_STEPS, FRAME_LINKS: set by the page; pages.py _frame_lists, _unwritten,
    _calibration_links say it alike); the steps' table's bars follow the job's progress, and the table is asked
    from the server again when the job's entries (and their steps) are not those it was laid out for -#}
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
  function setBar(tr, done, total){
    const bar = tr && tr.querySelector('progress');
    if (!bar) return;
    bar.max = Math.max(total, 1); bar.value = Math.min(done, bar.max);
    tr.querySelector('.count').textContent = done + '/' + total;
  }
  let relayout = null;  // (the steps table asked from the server, once at a time)
  function renderSteps(j){
    // every entry's row by data-step, every step's by data-group (the sum of its entries); entries the table was
    // not laid out for (their steps as the record says: pages.steps_key) have the server lay it out again
    const entries = Object.entries(j.progress || {});
    const key = JSON.stringify(entries.map(([n, p]) => [n, p.step || n]));
    let table = document.getElementById('steps');
    if (table.dataset.key !== key && !relayout)
      relayout = fetch(location.pathname, {headers: {'Accept': 'text/html'}})
        .then(r => r.ok ? r.text() : null).then(t => {
          const fresh = t && new DOMParser().parseFromString(t, 'text/html').getElementById('steps');
          if (fresh) document.getElementById('steps').replaceWith(document.adoptNode(fresh));
        }).catch(() => {}).finally(() => { relayout = null; });
    table = document.getElementById('steps');
    const sums = {};
    for (const [name, p] of entries){
      setBar(table.querySelector('tr[data-step="' + CSS.escape(name) + '"]'), p.done, p.total);
      const s = sums[p.step || name] = sums[p.step || name] || [0, 0];
      s[0] += p.done; s[1] += p.total;
    }
    for (const [step, [done, total]] of Object.entries(sums))
      setBar(table.querySelector('tbody[data-group="' + CSS.escape(step) + '"] tr.step'), done, total);
    return table.dataset.key === key;
  }
  function render(j){
    const st = document.getElementById('state');
    st.textContent = j.state + (j.cancel_requested && !TERMINAL.includes(j.state) ? ' (cancel requested)' : '');
    st.className = 'state state-' + j.state;
    const box = document.getElementById('cancel-box');
    if (box) box.hidden = TERMINAL.includes(j.state) || !!j.cancel_requested;
    setBar(document.getElementById('bar-all').parentElement, j.done, j.total);
    const laidOut = renderSteps(j);
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
    return !TERMINAL.includes(j.state) || !laidOut;  // (a finished job's until its steps' table is laid out)
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
