{#- polls /jobs every second while a listed job is active, updating states and bars (LIMIT: set by the page) -#}
(function(){
  const TERMINAL = ["done", "failed", "cancelled"];
  function update(jobs){
    let active = false;
    for (const j of jobs){
      const tr = document.querySelector('tr[data-job="' + j.id + '"]');
      if (!tr) continue;
      const st = tr.querySelector('.state');
      st.textContent = j.state; st.className = 'state state-' + j.state;
      // a failed job's first line of error beside its state: the list says why without a click
      tr.querySelector('.why').textContent = j.state === 'failed' && j.error ? j.error.split('\n')[0] : '';
      const bar = tr.querySelector('progress');
      bar.max = Math.max(j.total, 1); bar.value = Math.min(j.done, bar.max);
      tr.querySelector('.count').textContent = j.done + '/' + j.total;
      if (j.state === 'done' && j.kind === 'process'){
        const r = tr.querySelector('.report');
        if (!r.firstChild){ const a = document.createElement('a'); a.href = '/ui/jobs/' + j.id + '/report';
                            a.textContent = 'report'; r.appendChild(a); }
      }
      if (!TERMINAL.includes(j.state)) active = true;
    }
    return active;
  }
  async function poll(){
    try {
      const r = await fetch('/jobs?limit=' + LIMIT, {headers: {'Accept': 'application/json'}});
      if (r.ok && !update(await r.json())) return;
    } catch (e) {}
    setTimeout(poll, 1000);
  }
  if (document.querySelector('tr[data-job]')) setTimeout(poll, 1000);
})();
