// The depthmill operator console: jobs, submission, results in 3-D, telemetry, comparison.
// Everything goes through the documented REST API (/openapi.json); no build step.

const $ = (sel, root = document) => root.querySelector(sel);
const TOKEN_KEY = 'depthmill.token';
const ACTIVE = new Set(['queued', 'running']);
const STAGES = ['scan', 'reconstruct', 'plan', 'execute', 'report'];
const FIRST_STAGE = { mesh: 'scan', point_cloud: 'reconstruct', depth_map: 'plan', gcode: 'execute' };

// ---------------------------------------------------------------- helpers

function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === undefined || v === null || v === false) continue;
    if (k === 'class') el.className = v;
    else if (k === 'text') el.textContent = v;
    else if (k.startsWith('on')) el.addEventListener(k.slice(2), v);
    else if (k === 'dataset') Object.assign(el.dataset, v);
    else el.setAttribute(k, v === true ? '' : v);
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

function toast(message) {
  const box = h('div', { text: message });
  $('#toast').append(box);
  setTimeout(() => box.remove(), 6000);
}

function fmtTime(ms) {
  return ms ? new Date(ms).toLocaleString() : '';
}

function fmtDuration(s) {
  if (s === undefined || s === null || !isFinite(s)) return '';
  if (s < 60) return `${s.toFixed(1)} s`;
  const m = Math.floor(s / 60);
  return m < 60 ? `${m} min ${Math.round(s % 60)} s` : `${Math.floor(m / 60)} h ${m % 60} min`;
}

function fmtBytes(n) {
  if (n < 1024) return `${n} B`;
  const u = ['KiB', 'MiB', 'GiB'];
  let i = -1;
  do { n /= 1024; i++; } while (n >= 1024 && i < u.length - 1);
  return `${n.toFixed(1)} ${u[i]}`;
}

function fmtNum(v, digits = 4) {
  return typeof v === 'number' ? (Math.abs(v) >= 1000 ? v.toFixed(0) : Number(v.toPrecision(digits)).toString()) : String(v ?? '');
}

function badge(status) {
  return h('span', { class: `badge ${status}`, text: status });
}

function jobDuration(job) {
  const end = ACTIVE.has(job.status) ? Date.now() : job.updated_at_ms;
  return (end - job.created_at_ms) / 1000;
}

// ---------------------------------------------------------------- API and token

class ApiError extends Error {
  constructor(status, body) {
    const e = (body && body.error) || {};
    super(e.message || `HTTP ${status}`);
    this.status = status;
    this.code = e.code;
    this.field = e.field;
  }
}

let tokenWaiters = null;

function askToken(message) {
  if (tokenWaiters) return new Promise((resolve) => tokenWaiters.push(resolve));
  tokenWaiters = [];
  const dialog = $('#token-dialog');
  $('#token-error').textContent = message || '';
  $('#token-input').value = '';
  return new Promise((resolve) => {
    tokenWaiters.push(resolve);
    const done = (ev) => {
      ev.preventDefault();
      const value = $('#token-input').value.trim();
      if (!value) return;
      sessionStorage.setItem(TOKEN_KEY, value);
      $('#token-form').removeEventListener('submit', done);
      dialog.close();
      $('#token-button').hidden = false;
      const waiters = tokenWaiters;
      tokenWaiters = null;
      waiters.forEach((w) => w(value));
    };
    $('#token-form').addEventListener('submit', done);
    dialog.showModal();
    $('#token-input').focus();
  });
}

async function request(path, opts = {}, retry = true) {
  const headers = new Headers(opts.headers || {});
  const token = sessionStorage.getItem(TOKEN_KEY);
  if (token) headers.set('Authorization', `Bearer ${token}`);
  const resp = await fetch(path, { ...opts, headers });
  if (resp.status === 401 && retry) {
    let why = token ? 'The token was refused.' : '';
    try { why = (await resp.json()).error.message || why; } catch (_) { /* not JSON */ }
    await askToken(why);
    return request(path, opts, false);
  }
  return resp;
}

async function api(path, opts = {}) {
  const resp = await request(path, opts);
  let body = null;
  const type = resp.headers.get('content-type') || '';
  if (type.includes('json')) body = await resp.json();
  if (!resp.ok) throw new ApiError(resp.status, body);
  return body;
}

// Server-sent events of a job through fetch (EventSource cannot send the token).
function watchJob(id, onJob) {
  const ctrl = new AbortController();
  (async () => {
    try {
      const resp = await request(`/v1/jobs/${encodeURIComponent(id)}/events`, { signal: ctrl.signal });
      if (!resp.ok || !resp.body) return;
      const reader = resp.body.getReader();
      const dec = new TextDecoder();
      let buf = '';
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buf += dec.decode(value, { stream: true });
        let end;
        while ((end = buf.indexOf('\n\n')) >= 0) {
          const event = buf.slice(0, end);
          buf = buf.slice(end + 2);
          const data = event.split('\n').filter((l) => l.startsWith('data:')).map((l) => l.slice(5).trim()).join('\n');
          if (data) {
            try { onJob(JSON.parse(data)); } catch (_) { /* keep-alive or partial */ }
          }
        }
      }
    } catch (e) {
      if (e.name !== 'AbortError') console.warn('events', e);
    }
  })();
  return () => ctrl.abort();
}

async function download(art, name) {
  const resp = await request(`/v1/artifacts/${art.sha256}`);
  if (!resp.ok) throw new ApiError(resp.status, null);
  const blob = await resp.blob();
  const url = URL.createObjectURL(blob);
  const a = h('a', { href: url, download: name });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

async function artifactBytes(art) {
  const resp = await request(`/v1/artifacts/${art.sha256}`);
  if (!resp.ok) throw new ApiError(resp.status, null);
  return resp.arrayBuffer();
}

// ---------------------------------------------------------------- router

let cleanup = [];
const routes = [
  [/^#\/jobs\/([^/?]+)$/, (m) => jobPage(decodeURIComponent(m[1]))],
  [/^#\/submit$/, () => submitPage()],
  [/^#\/compare(?:\?(.*))?$/, (m) => comparePage(new URLSearchParams(m[1] || ''))],
  [/^(#\/jobs)?(?:\?(.*))?$/, (m) => jobsPage(new URLSearchParams(m[2] || ''))],
];

async function route() {
  cleanup.forEach((f) => f());
  cleanup = [];
  const hash = location.hash || '#/jobs';
  const main = $('#main');
  for (const a of document.querySelectorAll('[data-nav]')) {
    a.toggleAttribute('aria-current', hash.startsWith(`#/${a.dataset.nav}`));
    if (a.hasAttribute('aria-current')) a.setAttribute('aria-current', 'page');
  }
  for (const [re, view] of routes) {
    const m = hash.match(re);
    if (m) {
      main.replaceChildren(h('p', { class: 'muted', text: 'Loading…' }));
      try {
        const content = await view(m);
        main.replaceChildren(content);
      } catch (e) {
        main.replaceChildren(h('div', { class: 'card error', role: 'alert' }, h('strong', {}, 'Could not load this page: '), e.message));
      }
      main.focus({ preventScroll: true });
      return;
    }
  }
  main.replaceChildren(h('p', {}, 'No such page. ', h('a', { href: '#/jobs' }, 'Jobs')));
}

// ---------------------------------------------------------------- jobs list

async function jobsPage(params) {
  const status = params.get('status') || '';
  const root = h('section', { 'aria-labelledby': 'jobs-title' });
  const filter = h('select', { id: 'status-filter', 'aria-label': 'Status' },
    ['', 'queued', 'running', 'succeeded', 'failed', 'cancelled'].map((s) => h('option', { value: s, selected: s === status }, s || 'all')));
  filter.addEventListener('change', () => { location.hash = filter.value ? `#/jobs?status=${filter.value}` : '#/jobs'; });
  const tbody = h('tbody');
  const more = h('button', { type: 'button', hidden: true, text: 'Older jobs' });
  const count = h('span', { class: 'muted small' });
  root.append(
    h('div', { class: 'row' }, h('h2', { id: 'jobs-title', text: 'Jobs' }), h('span', { style: 'flex:1' }),
      h('label', { for: 'status-filter', class: 'muted small', text: 'Status' }), filter,
      h('a', { href: '#/submit' }, h('button', { type: 'button', class: 'primary', tabindex: '-1', text: 'New job' }))),
    h('div', { class: 'table-wrap' }, h('table', { id: 'jobs-table' },
      h('caption', { class: 'muted small', style: 'text-align:left;padding:.4rem .6rem' }, 'Newest first; running jobs update live. ', count),
      h('thead', {}, h('tr', {}, ['Name', 'Job', 'Status', 'Stage', 'Progress', 'Submitted', 'Time'].map((t, i) =>
        h('th', { scope: 'col', class: i === 6 ? 'num' : (i === 1 || i === 5 ? 'hide-narrow' : '') , text: t })))),
      tbody)),
    h('div', { class: 'row', style: 'margin-top:.6rem' }, more));

  const rows = new Map();
  const watching = new Map();
  const put = (job) => {
    const row = h('tr', { dataset: { id: job.id, status: job.status } },
      h('td', {}, h('a', { href: `#/jobs/${job.id}` }, job.name || '(unnamed)')),
      h('td', { class: 'hide-narrow' }, h('code', { class: 'small', text: job.id.slice(0, 8) })),
      h('td', {}, badge(job.status)),
      h('td', { text: job.stage }),
      h('td', {}, h('progress', { max: '1', value: String(job.progress), 'aria-label': `progress ${Math.round(job.progress * 100)} %` })),
      h('td', { class: 'hide-narrow small', text: fmtTime(job.created_at_ms) }),
      h('td', { class: 'num', text: fmtDuration(jobDuration(job)) }));
    const old = rows.get(job.id);
    if (old) old.replaceWith(row); else tbody.append(row);
    rows.set(job.id, row);
    if (ACTIVE.has(job.status) && !watching.has(job.id) && watching.size < 25) {
      watching.set(job.id, watchJob(job.id, put));
    }
    if (!ACTIVE.has(job.status) && watching.has(job.id)) {
      watching.get(job.id)();
      watching.delete(job.id);
    }
    count.textContent = `${rows.size} shown`;
  };
  cleanup.push(() => watching.forEach((stop) => stop()));

  let cursor = null;
  const load = async () => {
    const q = new URLSearchParams({ limit: '50' });
    if (status) q.set('status', status);
    if (cursor) q.set('cursor', cursor);
    const page = await api(`/v1/jobs?${q}`);
    page.jobs.forEach(put);
    cursor = page.next_cursor || null;
    more.hidden = !cursor;
  };
  more.addEventListener('click', () => load().catch((e) => toast(e.message)));
  await load();
  if (rows.size === 0) tbody.append(h('tr', {}, h('td', { colspan: '7', class: 'muted' }, 'No jobs yet. ', h('a', { href: '#/submit' }, 'Submit one'), '.')));
  // New jobs appear without a reload: the first page again every 5 s.
  const timer = setInterval(async () => {
    try {
      const q = new URLSearchParams({ limit: '50' });
      if (status) q.set('status', status);
      const page = await api(`/v1/jobs?${q}`);
      for (const job of page.jobs.reverse()) {
        if (!rows.has(job.id)) {
          put(job);
          tbody.prepend(rows.get(job.id));
        } else if (!watching.has(job.id)) put(job);
      }
    } catch (_) { /* next time */ }
  }, 5000);
  cleanup.push(() => clearInterval(timer));
  return root;
}

// ---------------------------------------------------------------- job page

async function jobPage(id) {
  let job = await api(`/v1/jobs/${encodeURIComponent(id)}`);
  const root = h('section', { 'aria-labelledby': 'job-title' });
  const head = h('div');
  const body = h('div');
  root.append(head, body);
  let shownStatus = null;
  const render = (j) => {
    job = j;
    head.replaceChildren(jobHeader(j));
    if (shownStatus !== j.status || ACTIVE.has(j.status)) {
      body.replaceChildren(jobDetails(j));
      shownStatus = j.status;
    }
  };
  render(job);
  if (ACTIVE.has(job.status)) cleanup.push(watchJob(id, render));
  return root;
}

function jobHeader(job) {
  const cancel = h('button', { type: 'button', class: 'danger', id: 'cancel-job', text: 'Cancel job', disabled: !ACTIVE.has(job.status) || job.cancel_requested });
  cancel.addEventListener('click', async () => {
    cancel.disabled = true;
    try { await api(`/v1/jobs/${job.id}/cancel`, { method: 'POST' }); toast('Cancel requested'); } catch (e) { toast(e.message); cancel.disabled = false; }
  });
  return h('div', { class: 'card' },
    h('div', { class: 'row' },
      h('h2', { id: 'job-title', style: 'margin:0' }, job.name || '(unnamed job)'), badge(job.status), h('span', { style: 'flex:1' }),
      h('a', { href: `#/compare?a=${job.id}` }, 'Compare…'), cancel),
    h('dl', { class: 'kv small', style: 'margin-top:.6rem' },
      h('dt', { text: 'Job' }), h('dd', {}, h('code', { text: job.id })),
      h('dt', { text: 'Stage' }), h('dd', {}, `${job.stage} `, h('progress', { max: '1', value: String(job.progress), 'aria-label': 'progress' }), ` ${Math.round(job.progress * 100)} %`),
      h('dt', { text: 'Input' }), h('dd', { text: `${job.spec.input.kind} ${job.spec.input.artifact.slice(0, 12)}…` }),
      h('dt', { text: 'Submitted' }), h('dd', { text: `${fmtTime(job.created_at_ms)} (${fmtDuration(jobDuration(job))})` }),
      job.error ? [h('dt', { text: 'Error' }), h('dd', { class: 'error', role: 'alert', id: 'job-error' }, `${job.error.stage}: ${job.error.code}: ${job.error.message}`)] : null));
}

function jobDetails(job) {
  const wrap = h('div');
  const timings = Object.entries(job.stage_timings_s || {}).sort((x, y) => STAGES.indexOf(x[0]) - STAGES.indexOf(y[0]));
  const metrics = Object.entries(job.metrics || {});
  wrap.append(h('div', { class: 'grid2' },
    h('div', { class: 'card' }, h('h3', { text: 'Stages' }),
      h('table', {}, h('thead', {}, h('tr', {}, h('th', { text: 'Stage' }), h('th', { class: 'num', text: 'Time' }))),
        h('tbody', {}, timings.length ? timings.map(([s, t]) => h('tr', {}, h('td', { text: s }), h('td', { class: 'num', text: fmtDuration(t) })))
          : h('tr', {}, h('td', { colspan: '2', class: 'muted', text: 'No stage finished yet' }))))),
    h('div', { class: 'card' }, h('h3', { text: 'Figures' }),
      metrics.length ? h('table', { id: 'metrics' }, h('tbody', {}, metrics.map(([k, v]) => h('tr', {}, h('th', { scope: 'row', text: k }), h('td', { class: 'num', text: fmtNum(v) })))))
        : h('p', { class: 'muted', text: 'None yet' }))));

  const diags = job.diagnostics || [];
  if (diags.length) {
    wrap.append(h('div', { class: 'card' }, h('h3', { text: 'What the stages found' }),
      h('div', { class: 'table-wrap' }, h('table', { id: 'diagnostics' },
        h('thead', {}, h('tr', {}, ['Stage', 'Code', 'Message'].map((t) => h('th', { scope: 'col', text: t })))),
        h('tbody', {}, diags.map((d) => h('tr', {},
          h('td', { text: d.stage }), h('td', {}, h('code', { text: d.code })), h('td', { class: 'small', text: d.message }))))))));
  }

  wrap.append(h('div', { class: 'card' }, h('h3', { text: 'Attempts' }),
    h('div', { class: 'table-wrap' }, h('table', { id: 'attempts' },
      h('thead', {}, h('tr', {}, ['Stage', '#', 'Outcome', 'Started', 'Time', 'Error'].map((t) => h('th', { scope: 'col', text: t })))),
      h('tbody', {}, (job.attempts || []).map((a) => h('tr', {},
        h('td', { text: a.stage }), h('td', { text: a.attempt }), h('td', {}, badge(a.outcome === 'ok' ? 'succeeded' : a.outcome === 'running' ? 'running' : 'failed')),
        h('td', { class: 'small', text: fmtTime(a.started_at_ms) }),
        h('td', { class: 'num', text: a.finished_at_ms ? fmtDuration((a.finished_at_ms - a.started_at_ms) / 1000) : '' }),
        h('td', { class: 'small' }, a.error_code ? `${a.error_code}: ${a.error_message || ''}` : ''))))))));

  const arts = Object.entries(job.artifacts || {});
  wrap.append(h('div', { class: 'card' }, h('h3', { text: 'Artifacts' }),
    arts.length ? h('div', { class: 'table-wrap' }, h('table', { id: 'artifacts' },
      h('thead', {}, h('tr', {}, ['Name', 'Type', 'Size', ''].map((t) => h('th', { scope: 'col', text: t })))),
      h('tbody', {}, arts.map(([name, art]) => {
        const b = h('button', { type: 'button', text: 'Download', 'aria-label': `Download ${name}` });
        b.addEventListener('click', () => download(art, `${name}${extension(art.media_type)}`).catch((e) => toast(e.message)));
        return h('tr', {}, h('td', {}, h('code', { text: name })), h('td', { class: 'small', text: art.media_type }), h('td', { class: 'num', text: fmtBytes(art.size) }), h('td', {}, b));
      })))) : h('p', { class: 'muted', text: 'None yet' })));

  // Tabs: 3-D view, telemetry, report.
  const panels = [
    ['view', '3-D view', () => viewerPanel(job)],
    ['telemetry', 'Telemetry', () => telemetryPanel(job)],
    ['report', 'Report', () => reportPanel(job)],
  ];
  const tabs = h('div', { class: 'tabs', role: 'tablist', 'aria-label': 'Results' });
  const panel = h('div', { class: 'tabpanel', role: 'tabpanel', id: 'result-panel', tabindex: '0' });
  let stopPanel = null;
  const show = async (key) => {
    for (const b of tabs.children) b.setAttribute('aria-selected', String(b.dataset.tab === key));
    if (stopPanel) { stopPanel(); stopPanel = null; }
    panel.replaceChildren(h('p', { class: 'muted', text: 'Loading…' }));
    try {
      const [node, stop] = await panels.find((p) => p[0] === key)[2]();
      panel.replaceChildren(node);
      stopPanel = stop || null;
    } catch (e) {
      panel.replaceChildren(h('p', { class: 'error', role: 'alert', text: e.message }));
    }
  };
  cleanup.push(() => stopPanel && stopPanel());
  for (const [key, label] of panels) {
    const b = h('button', { type: 'button', role: 'tab', id: `tab-${key}`, dataset: { tab: key }, 'aria-controls': 'result-panel', text: label });
    b.addEventListener('click', () => show(key));
    tabs.append(b);
  }
  wrap.append(tabs, panel);
  show(ACTIVE.has(job.status) ? 'telemetry' : 'view');
  return wrap;
}

function extension(mediaType) {
  return ({ 'application/x-ply': '.ply', 'model/stl': '.stl', 'model/obj': '.obj', 'model/x-off': '.off', 'application/x-pcd': '.pcd', 'image/png': '.png', 'text/x-gcode': '.ngc', 'text/csv': '.csv',
    'application/json': '.json', 'text/html': '.html', 'application/x-npy': '.npy', 'text/x-xyz': '.xyz', 'image/svg+xml': '.svg' })[mediaType] || '';
}

async function reportPanel(job) {
  const resp = await request(`/v1/jobs/${job.id}/report`);
  if (!resp.ok) throw new ApiError(resp.status, await resp.json().catch(() => null));
  const html = await resp.text();
  const frame = h('iframe', { class: 'report', title: `Report of job ${job.name || job.id}`, sandbox: 'allow-scripts' });
  frame.srcdoc = html;
  return [frame];
}

// ---------------------------------------------------------------- telemetry

function parseCsv(text) {
  const lines = text.split('\n').filter((l) => l.trim());
  const head = lines[0].split(',');
  const cols = head.map(() => []);
  for (let i = 1; i < lines.length; i++) {
    const cells = lines[i].split(',');
    for (let c = 0; c < head.length; c++) {
      const v = Number(cells[c]);
      cols[c].push(Number.isFinite(v) ? v : cells[c]);
    }
  }
  return Object.fromEntries(head.map((name, i) => [name, cols[i]]));
}

async function telemetryPanel(job) {
  const art = job.artifacts && job.artifacts.telemetry;
  if (!art) return [h('p', { class: 'muted', text: ACTIVE.has(job.status) ? 'Telemetry appears when the execute stage has run.' : 'This job has no telemetry (it did not reach the execute stage).' })];
  const { default: uPlot } = await import('uplot');
  const t = parseCsv(new TextDecoder().decode(await artifactBytes(art)));
  const wrap = h('div', { id: 'telemetry' });
  const width = Math.max(320, Math.min(1300, ($('#main').clientWidth || 1000) - 60));
  const series = [
    ['Cutting torque (N·m)', [['torque_true_nm', 'true', '#cf222e'], ['torque_from_current_nm', 'from current', '#1f6feb']]],
    ['Feed (mm/min)', [['feed_mm_min', 'feed', '#1a7f37']]],
    ['Spindle (rpm)', [['spindle_rpm', 'speed', '#8250df']]],
    ['Power (W)', [['power_w', 'power', '#9a6700']]],
  ];
  const plots = [];
  for (const [title, ys] of series) {
    if (!ys.every(([k]) => t[k])) continue;
    const box = h('figure', { style: 'margin:0 0 1rem' }, h('figcaption', { class: 'small', text: title }));
    wrap.append(box);
    plots.push(new uPlot({
      width, height: 170,
      scales: { x: { time: false } },
      axes: [{ label: 'time (s)' }, {}],
      series: [{ label: 't (s)' }, ...ys.map(([, label, stroke]) => ({ label, stroke, width: 1 }))],
    }, [t.time_s, ...ys.map(([k]) => t[k])], box));
  }
  // The adaptive loop's decisions: which limit was active, and for how long.
  if (t.active) {
    const spans = new Map();
    for (let i = 1; i < t.time_s.length; i++) {
      const k = String(t.active[i] || 'none');
      spans.set(k, (spans.get(k) || 0) + (t.time_s[i] - t.time_s[i - 1]));
    }
    wrap.append(h('h4', { text: 'Active limit of the adaptive loop' }),
      h('table', { id: 'active-limits' }, h('tbody', {}, [...spans.entries()].sort((a, b) => b[1] - a[1]).map(([k, s]) =>
        h('tr', {}, h('td', { text: k }), h('td', { class: 'num', text: fmtDuration(s) }))))));
  }
  wrap.append(h('p', { class: 'muted small', text: `${t.time_s.length} rows; policy ${job.spec.execute?.adaptive || 'aco'}.` }));
  return [wrap, () => plots.forEach((p) => p.destroy())];
}

// ---------------------------------------------------------------- 3-D view

function parseGcode(text) {
  // Moves as segments, grouped into passes by tool change and by comments naming a pass.
  const passes = [];
  let cur = null;
  let pos = [NaN, NaN, NaN];
  let motion = 0;
  let absolute = true;
  let plane = 17;
  let scale = 1;
  let label = 'program';
  const newPass = (name) => { cur = { name, rapid: [], cut: [] }; passes.push(cur); };
  newPass(label);
  for (const raw of text.split('\n')) {
    const comment = raw.match(/\(([^)]*)\)/);
    if (comment && /rough|finish|rest|pass|contour|face/i.test(comment[1])) { label = comment[1].trim(); newPass(label); }
    const line = raw.replace(/\([^)]*\)/g, '').replace(/;.*/, '').toUpperCase();
    const words = [...line.matchAll(/([A-Z])\s*([-+]?\d*\.?\d+)/g)].map((m) => [m[1], Number(m[2])]);
    if (!words.length) continue;
    const next = pos.slice();
    let hasAxis = false;
    let machineCoords = false;
    for (const [l, v] of words) {
      if (l === 'G') {
        if ([0, 1, 2, 3].includes(v)) motion = v;
        if (v === 90) absolute = true;
        if (v === 91) absolute = false;
        if (v === 20) scale = 25.4;
        if (v === 21) scale = 1;
        if (v === 53 || v === 28 || v === 30) machineCoords = true;
        if (v === 17 || v === 18 || v === 19) plane = v;
      } else if (l === 'T') { newPass(`${label} T${v}`); }
      const axis = 'XYZ'.indexOf(l);
      if (axis >= 0) { next[axis] = absolute ? v * scale : pos[axis] + v * scale; hasAxis = true; }
    }
    if (!hasAxis) continue;
    if (machineCoords) {
      // Machine coordinates or a reference return: the named axes end where this reading does
      // not know (the top of the machine for Z).
      for (const [l] of words) { const axis = 'XYZ'.indexOf(l); if (axis >= 0) next[axis] = NaN; }
      pos = next;
      continue;
    }
    // A rapid from an unknown height passes over everything: it moves the tool, it is not drawn.
    if (next.every(Number.isFinite) && pos.every(Number.isFinite)) {
      const out = motion === 0 ? cur.rapid : cur.cut;
      const word = (l) => { const w = words.find((x) => x[0] === l); return w ? w[1] * scale : undefined; };
      if ((motion === 2 || motion === 3) && plane === 17) {
        for (const p of arcPoints(pos, next, word('I'), word('J'), word('R'), motion === 2)) { out.push(...p); }
      } else {
        out.push(...pos, ...next);
      }
    }
    pos = next;
  }
  return passes.filter((p) => p.cut.length || p.rapid.length);
}

// An XY arc from `a` to `b` (centre offset I, J from `a`, or radius R: negative the long way) as
// line segments (pairs of points), about 5° each; a helix when Z changes.
function arcPoints(a, b, i, j, r, clockwise) {
  let cx, cy;
  if (i !== undefined || j !== undefined) {
    cx = a[0] + (i || 0); cy = a[1] + (j || 0);
  } else if (r !== undefined) {
    const dx = b[0] - a[0], dy = b[1] - a[1], d = Math.hypot(dx, dy);
    if (d === 0 || Math.abs(r) < d / 2) return [a, b];
    const hgt = Math.sqrt(r * r - d * d / 4) * ((r > 0) === clockwise ? -1 : 1);
    cx = a[0] + dx / 2 - hgt * dy / d; cy = a[1] + dy / 2 + hgt * dx / d;
  } else {
    return [a, b];
  }
  const a0 = Math.atan2(a[1] - cy, a[0] - cx), a1 = Math.atan2(b[1] - cy, b[0] - cx);
  let sweep = a1 - a0;
  if (clockwise && sweep >= 0) sweep -= 2 * Math.PI;
  if (!clockwise && sweep <= 0) sweep += 2 * Math.PI;
  const rad = Math.hypot(a[0] - cx, a[1] - cy);
  const n = Math.max(2, Math.ceil(Math.abs(sweep) / (Math.PI / 36)));
  const pts = [];
  let prev = a;
  for (let k = 1; k <= n; k++) {
    const t = k / n, ang = a0 + sweep * t;
    const p = k === n ? b : [cx + rad * Math.cos(ang), cy + rad * Math.sin(ang), a[2] + (b[2] - a[2]) * t];
    pts.push(prev, p);
    prev = p;
  }
  return pts;
}

// A depth-map PNG as heights (mm, NaN without data) on a grid of at most ~400 cells a side.
async function decodeMap(art, maxSide = 400) {
  const bytes = new Uint8Array(await artifactBytes(art));
  const meta = pngMeta(bytes);
  const img = await createImageBitmap(new Blob([bytes], { type: 'image/png' }), { colorSpaceConversion: 'none', premultiplyAlpha: 'none' });
  const step = Math.max(1, Math.ceil(Math.max(img.width, img.height) / maxSide));
  const w = Math.ceil(img.width / step), hgt = Math.ceil(img.height / step);
  const canvas = new OffscreenCanvas(w, hgt);
  const ctx = canvas.getContext('2d');
  ctx.drawImage(img, 0, 0, w, hgt);
  const px = ctx.getImageData(0, 0, w, hgt).data;
  const z0 = meta.z_min_mm ?? 0, z1 = meta.z_max_mm ?? 1;
  const z = new Float32Array(w * hgt);
  for (let i = 0; i < w * hgt; i++) z[i] = px[i * 4 + 3] > 0 ? z0 + (px[i * 4] / 255) * (z1 - z0) : NaN;
  return { w, hgt, z, meta, p: (meta.pixel_mm || 0.1) * (img.width / w) };
}

// A surface over a decoded map (`lift` added to its heights where given), coloured per vertex
// by `colour(i)` or plain.
function mapSurface(THREE, m, lift, colour) {
  const { w, hgt, z, meta, p } = m;
  const ox = meta.origin_x_mm ?? 0, oy = meta.origin_y_mm ?? 0;
  const pos = new Float32Array(w * hgt * 3);
  const valid = new Uint8Array(w * hgt);
  const colours = colour ? new Float32Array(w * hgt * 3) : null;
  for (let r = 0; r < hgt; r++) {
    for (let c = 0; c < w; c++) {
      const i = r * w + c;
      const zz = z[i] + (lift ? lift[i] : 0);
      valid[i] = Number.isFinite(zz) ? 1 : 0;
      // Images show +Y up: row 0 of the picture is the map's last row.
      pos.set([ox + (c + 0.5) * p, oy + (hgt - r - 0.5) * p, valid[i] ? zz : 0], i * 3);
      if (colours) colours.set(colour(i), i * 3);
    }
  }
  const index = [];
  for (let r = 0; r + 1 < hgt; r++) for (let c = 0; c + 1 < w; c++) {
    const a = r * w + c, b = a + 1, d = a + w, e = d + 1;
    if (valid[a] && valid[b] && valid[d] && valid[e]) index.push(a, d, b, b, d, e);
  }
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(pos, 3));
  if (colours) g.setAttribute('color', new THREE.BufferAttribute(colours, 3));
  g.setIndex(index);
  g.computeVertexNormals();
  const material = colours
    ? new THREE.MeshStandardMaterial({ vertexColors: true, side: THREE.DoubleSide, roughness: 0.75 })
    : new THREE.MeshStandardMaterial({ color: 0xb8c4d0, side: THREE.DoubleSide, roughness: 0.8 });
  return new THREE.Mesh(g, material);
}

// depthmill's metadata in a PNG: `tEXt` chunks keyed `depthmill:pixel_mm`, `depthmill:z_min_mm`, ...
function pngMeta(bytes) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const meta = {};
  let off = 8;
  while (off + 12 <= bytes.length) {
    const len = view.getUint32(off);
    const type = String.fromCharCode(...bytes.subarray(off + 4, off + 8));
    if (type === 'tEXt') {
      const data = bytes.subarray(off + 8, off + 8 + len);
      const nul = data.indexOf(0);
      const key = new TextDecoder('latin1').decode(data.subarray(0, nul));
      const value = new TextDecoder('latin1').decode(data.subarray(nul + 1));
      if (key.startsWith('depthmill:')) {
        const n = Number(value);
        meta[key.slice(10)] = Number.isFinite(n) ? n : value;
      }
    }
    if (type === 'IEND') break;
    off += 12 + len;
  }
  return meta;
}

function deviationColour(d, range) {
  if (!Number.isFinite(d)) return [0.6, 0.6, 0.6];
  const t = Math.max(-1, Math.min(1, d / range));
  // Red: cut into the part (negative); blue: material left (positive); white: on size.
  return t < 0 ? [1, 1 + t, 1 + t] : [1 - t, 1 - t, 1];
}

async function viewerPanel(job) {
  const arts = job.artifacts || {};
  const layers = [
    ['cloud', 'Scanned cloud', arts.point_cloud],
    ['map', 'Depth map', arts.depth_map],
    ['paths', 'Toolpaths', arts.gcode],
    ['part', 'Machined part (deviation)', arts.machined_part_view],
    // A 3-axis job: the machined surface on the depth map's grid (target + deviation).
    ['machined', 'Machined surface (deviation)', !arts.machined_part_view && arts.depth_map && arts.deviation_map],
  ].filter((l) => l[2]);
  if (!layers.length) return [h('p', { class: 'muted', text: 'Nothing to show in 3-D yet.' })];
  const THREE = await import('three');
  const { OrbitControls } = await import('three/addons/controls/OrbitControls.js');
  const { PLYLoader } = await import('three/addons/loaders/PLYLoader.js');

  const box = h('div', { class: 'viewer', id: 'viewer', role: 'img', 'aria-label': '3-D view of the job: drag to orbit, wheel to zoom, arrow keys to pan' });
  const status = h('p', { class: 'muted small', id: 'viewer-status', 'aria-live': 'polite' });
  const legend = h('div', { class: 'legend' });
  const toggles = h('fieldset', { class: 'layers' }, h('legend', { text: 'Layers' }));
  const wrap = h('div', {}, toggles, box, legend, status);

  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
  box.append(renderer.domElement);
  renderer.domElement.tabIndex = 0;
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x1b2128);
  const camera = new THREE.PerspectiveCamera(40, 16 / 9, 0.1, 1e5);
  camera.up.set(0, 0, 1);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 1.6));
  const sun = new THREE.DirectionalLight(0xffffff, 1.4);
  sun.position.set(1, -1, 2);
  scene.add(sun);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.listenToKeyEvents(renderer.domElement);
  const groups = {};
  let frame = 0;
  const draw = () => {
    const w = box.clientWidth || 800, hh = box.clientHeight || 480;
    if (renderer.domElement.width !== Math.floor(w * renderer.getPixelRatio())) {
      renderer.setSize(w, hh, false);
      camera.aspect = w / hh;
      camera.updateProjectionMatrix();
    }
    renderer.render(scene, camera);
    box.dataset.frames = String(++frame);
  };
  controls.addEventListener('change', draw);

  const ply = new PLYLoader();
  ply.setCustomPropertyNameMapping({ deviation: ['deviation'] });
  const loaded = [];
  for (const [key, label, art] of layers) {
    const group = new THREE.Group();
    groups[key] = group;
    scene.add(group);
    // The depth map and the machined surface overlap: the machined one is shown first.
    const input = h('input', { type: 'checkbox', id: `layer-${key}`, checked: key !== 'map' || !(arts.machined_part_view || arts.deviation_map) });
    input.addEventListener('change', () => { group.visible = input.checked; draw(); });
    group.visible = input.checked;
    toggles.append(h('label', { for: `layer-${key}` }, input, ` ${label}`));
    loaded.push((async () => {
      try {
        if (key === 'cloud') {
          const g = ply.parse(await artifactBytes(art));
          const n = g.getAttribute('position').count;
          group.add(new THREE.Points(g, new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, color: 0x7ee787 })));
          return `${n} points`;
        }
        if (key === 'map') {
          group.add(mapSurface(THREE, await decodeMap(art)));
          return 'depth map';
        }
        if (key === 'machined') {
          const [target, dev] = await Promise.all([decodeMap(arts.depth_map), decodeMap(arts.deviation_map)]);
          if (dev.w !== target.w || dev.hgt !== target.hgt) return 'deviation map on another grid';
          const range = Math.max(Math.abs(dev.meta.z_min_mm ?? 0), Math.abs(dev.meta.z_max_mm ?? 0), 0.01);
          group.add(mapSurface(THREE, target, dev.z, (i) => deviationColour(dev.z[i], range)));
          legend.append(h('span', {}, h('i', { style: 'background:#ff4040' }), `gouge (−${fmtNum(range, 2)} mm)`),
            h('span', {}, h('i', { style: 'background:#fff' }), 'on size'),
            h('span', {}, h('i', { style: 'background:#4040ff' }), `material left (+${fmtNum(range, 2)} mm)`));
          return 'machined surface';
        }
        if (key === 'paths') {
          const passes = parseGcode(new TextDecoder().decode(await artifactBytes(art)));
          const colours = [0xf0883e, 0x58a6ff, 0xd2a8ff, 0x3fb950, 0xffa198, 0xe3b341];
          passes.forEach((p, i) => {
            const colour = colours[i % colours.length];
            if (p.cut.length) {
              const g = new THREE.BufferGeometry();
              g.setAttribute('position', new THREE.Float32BufferAttribute(p.cut, 3));
              group.add(new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: colour })));
            }
            if (p.rapid.length) {
              const g = new THREE.BufferGeometry();
              g.setAttribute('position', new THREE.Float32BufferAttribute(p.rapid, 3));
              group.add(new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: 0x6e7681, transparent: true, opacity: 0.35 })));
            }
            legend.append(h('span', {}, h('i', { style: `background:#${colour.toString(16).padStart(6, '0')}` }), p.name));
          });
          legend.append(h('span', {}, h('i', { style: 'background:#6e7681' }), 'rapids'));
          return `${passes.length} passes`;
        }
        if (key === 'part') {
          const g = ply.parse(await artifactBytes(art));
          const dev = g.getAttribute('deviation');
          const n = g.getAttribute('position').count;
          const colours = new Float32Array(n * 3);
          let range = 0;
          if (dev) for (let i = 0; i < n; i++) { const d = dev.getX(i); if (Number.isFinite(d)) range = Math.max(range, Math.abs(d)); }
          range = Math.max(range, 0.01);
          for (let i = 0; i < n; i++) colours.set(deviationColour(dev ? dev.getX(i) : NaN, range), i * 3);
          g.setAttribute('color', new THREE.BufferAttribute(colours, 3));
          g.computeVertexNormals();
          group.add(new THREE.Mesh(g, new THREE.MeshStandardMaterial({ vertexColors: true, roughness: 0.7, side: THREE.DoubleSide })));
          legend.append(h('span', {}, h('i', { style: 'background:#ff4040' }), `into the part (−${fmtNum(range, 2)} mm)`),
            h('span', {}, h('i', { style: 'background:#fff' }), 'on size'),
            h('span', {}, h('i', { style: 'background:#4040ff' }), `material left (+${fmtNum(range, 2)} mm)`),
            h('span', {}, h('i', { style: 'background:#999' }), 'not measured'));
          return `${g.index ? g.index.count / 3 : n / 3} triangles`;
        }
      } catch (e) {
        return `${label}: ${e.message}`;
      }
      return '';
    })());
  }
  const notes = await Promise.all(loaded);
  // Frame everything loaded.
  const bounds = new THREE.Box3().setFromObject(scene);
  if (!bounds.isEmpty()) {
    const c = bounds.getCenter(new THREE.Vector3());
    const size = bounds.getSize(new THREE.Vector3()).length() || 10;
    controls.target.copy(c);
    camera.position.set(c.x + size * 0.6, c.y - size * 0.9, c.z + size * 0.7);
    camera.near = size / 1000;
    camera.far = size * 20;
    camera.updateProjectionMatrix();
    controls.update();
  }
  status.textContent = notes.filter(Boolean).join(' · ');
  box.dataset.layers = layers.map((l) => l[0]).join(' ');
  const observer = new ResizeObserver(() => draw());
  observer.observe(box);
  requestAnimationFrame(draw);
  return [wrap, () => { observer.disconnect(); controls.dispose(); renderer.dispose(); }];
}

// ---------------------------------------------------------------- submit

// A mesh or cloud may be gzip-compressed (part.stl.gz): sent as it is, under its content's type.
function isGzipName(name) { return /\.gz$/i.test(name); }

function kindOf(file) {
  const parts = file.name.toLowerCase().split('.');
  const gz = parts.length > 2 && parts[parts.length - 1] === 'gz';
  if (gz) parts.pop();
  const ext = parts.length > 1 ? parts.pop() : '';
  const known = kindOfExt(ext);
  return gz && known && !['mesh', 'point_cloud', 'ply'].includes(known[0]) ? null : known;
}

function kindOfExt(ext) {
  return ({ stl: ['mesh', 'model/stl'], obj: ['mesh', 'model/obj'], off: ['mesh', 'model/x-off'], pcd: ['point_cloud', 'application/x-pcd'], xyz: ['point_cloud', 'text/x-xyz'], txt: ['point_cloud', 'text/x-xyz'], asc: ['point_cloud', 'text/x-xyz'],
    ply: ['ply', 'application/x-ply'], png: ['depth_map', 'image/png'], npy: ['depth_map', 'application/x-npy'],
    ngc: ['gcode', 'text/x-gcode'], nc: ['gcode', 'text/x-gcode'], gcode: ['gcode', 'text/x-gcode'], tap: ['gcode', 'text/x-gcode'], cnc: ['gcode', 'text/x-gcode'] })[ext] || null;
}

// A PLY file is a mesh when its header declares faces, a point cloud otherwise (as the CLI decides).
async function plyKind(file) {
  let bytes = await file.slice(0, 4096).arrayBuffer();
  if (isGzipName(file.name)) {
    // The header of the content: the first decompressed chunks, up to 4 KiB.
    const reader = file.stream().pipeThrough(new DecompressionStream('gzip')).getReader();
    const chunks = [];
    let n = 0;
    try {
      while (n < 4096) {
        const { value, done } = await reader.read();
        if (done) break;
        chunks.push(value);
        n += value.length;
      }
    } catch (e) {
      // A broken stream: the server names the fault when it reads the file.
    }
    reader.cancel().catch(() => {});
    const all = new Uint8Array(n);
    let at = 0;
    for (const c of chunks) { all.set(c, at); at += c.length; }
    bytes = all.slice(0, 4096).buffer;
  }
  const head = new TextDecoder().decode(bytes);
  const header = head.split('end_header')[0];
  const m = header.match(/element face (\d+)/);
  return m && Number(m[1]) > 0 ? 'mesh' : 'point_cloud';
}

let apiDoc = null;
async function schemas() {
  if (!apiDoc) apiDoc = await api('/openapi.json');
  return apiDoc.components.schemas;
}

// The schema of a property with its references and `null` alternatives taken away.
function resolve(all, s) {
  if (!s) return {};
  if (s.$ref) return { ...resolve(all, all[s.$ref.split('/').pop()]), description: s.description || all[s.$ref.split('/').pop()]?.description };
  for (const key of ['oneOf', 'anyOf']) {
    if (s[key]) {
      const alt = s[key].filter((x) => x.type !== 'null');
      if (alt.length === 1) return { ...resolve(all, alt[0]), description: s.description || alt[0].description };
      return { ...s, type: 'json' };
    }
  }
  if (s.allOf && s.allOf.length === 1) return resolve(all, s.allOf[0]);
  const type = Array.isArray(s.type) ? s.type.find((t) => t !== 'null') : s.type;
  return { ...s, type };
}

function fieldFor(all, path, name, schema, catalogs) {
  const s = resolve(all, schema);
  const id = `f-${path.replace(/\./g, '-')}`;
  const hint = s.description ? h('div', { class: 'hint', text: s.description.split('\n')[0] }) : null;
  let input;
  if (s.enum) {
    input = h('select', { id }, h('option', { value: '', text: '(default)' }), s.enum.map((v) => h('option', { value: v, text: v })));
  } else if (s.type === 'boolean') {
    input = h('select', { id }, h('option', { value: '', text: '(default)' }), h('option', { value: 'true', text: 'yes' }), h('option', { value: 'false', text: 'no' }));
  } else if (s.type === 'number' || s.type === 'integer') {
    input = h('input', { id, type: 'number', step: 'any', inputmode: 'decimal' });
  } else if (s.type === 'string') {
    input = h('input', { id, type: 'text', list: catalogs[name] ? `${id}-list` : null });
  } else {
    input = h('textarea', { id, rows: '2', placeholder: s.type === 'array' ? 'JSON list, e.g. [0, 90]' : 'JSON' });
  }
  input.dataset.field = path;
  input.dataset.type = s.enum ? 'string' : ['string', 'number', 'integer', 'boolean'].includes(s.type) ? s.type : 'json';
  // Tools, materials and machines from the catalog endpoints, as suggestions.
  const choices = catalogs[name] && s.type === 'string' ? h('datalist', { id: `${id}-list` }, catalogs[name].map((v) => h('option', { value: v }))) : null;
  const box = h('div', { class: 'field', dataset: { field: path } }, h('label', { for: id, text: name.replace(/_/g, ' ') }), input, choices, hint, h('div', { class: 'field-error', role: 'alert' }));
  return box;
}

function sectionForm(all, path, schema, catalogs, skip = []) {
  const s = resolve(all, schema);
  const fields = h('div', { class: 'fields' });
  const nested = [];
  for (const [name, prop] of Object.entries(s.properties || {})) {
    if (skip.includes(name)) continue;
    const r = resolve(all, prop);
    const p = path ? `${path}.${name}` : name;
    if (r.type === 'object' && r.properties) {
      nested.push(h('fieldset', { dataset: { section: p } }, h('legend', { text: name.replace(/_/g, ' ') }), sectionForm(all, p, prop, catalogs)));
    } else {
      fields.append(fieldFor(all, p, name, prop, catalogs));
    }
  }
  return h('div', {}, fields.children.length ? fields : null, nested);
}

function collect(form) {
  const out = {};
  for (const el of form.querySelectorAll('[data-field]:is(input, select, textarea)')) {
    // What the chosen process does not use is not sent.
    if (el.closest('[hidden]')) continue;
    const raw = el.value.trim();
    if (raw === '') continue;
    let v = raw;
    if (el.dataset.type === 'number' || el.dataset.type === 'integer') v = Number(raw);
    else if (el.dataset.type === 'boolean') v = raw === 'true';
    else if (el.dataset.type === 'json') { try { v = JSON.parse(raw); } catch (_) { v = raw; } }
    const keys = el.dataset.field.split('.');
    let o = out;
    keys.slice(0, -1).forEach((k) => { o = o[k] = o[k] || {}; });
    o[keys[keys.length - 1]] = v;
  }
  return out;
}

function showFieldError(form, field, message) {
  for (const f of form.querySelectorAll('.field.invalid')) { f.classList.remove('invalid'); $('.field-error', f).textContent = ''; }
  if (!field) return false;
  // The field itself, or the closest enclosing field the form has (`plan.faces.0.a_deg` -> `plan.faces`).
  const parts = field.split('.');
  let box = null;
  while (parts.length && !box) {
    box = form.querySelector(`.field[data-field="${CSS.escape(parts.join('.'))}"]`);
    parts.pop();
  }
  if (!box) return false;
  box.classList.add('invalid');
  $('.field-error', box).textContent = message;
  box.closest('details')?.setAttribute('open', '');
  $('input, select, textarea', box)?.focus();
  return true;
}

async function submitPage() {
  const all = await schemas();
  const catalogs = {};
  const [tools, materials, machines] = await Promise.all([
    api('/v1/tools').catch(() => null), api('/v1/materials').catch(() => null), api('/v1/machines').catch(() => null)]);
  if (tools) catalogs.tool = tools.tools.map((t) => t.name);
  if (materials) catalogs.material = materials.materials.map((m) => m.name);
  if (machines) catalogs.machine = machines.machines.map((m) => m.name);

  const fileInput = h('input', { type: 'file', id: 'file-input', accept: '.stl,.obj,.off,.ply,.pcd,.xyz,.txt,.asc,.gz,.png,.npy,.ngc,.nc,.gcode,.tap,.cnc', class: 'visually-hidden' });
  const drop = h('div', { class: 'drop', id: 'drop-zone', tabindex: '0', role: 'button', 'aria-describedby': 'drop-help' },
    h('strong', { text: 'Drop a part file here' }), h('br'), h('span', { id: 'drop-help', class: 'muted small', text: 'or press Enter to choose one: STL, PLY, XYZ (mesh or scan), PNG, NPY (depth map), NGC (G-code)' }));
  const fileStatus = h('p', { id: 'file-status', role: 'status', class: 'small' });
  const formBox = h('div');
  const root = h('section', { 'aria-labelledby': 'submit-title' }, h('h2', { id: 'submit-title', text: 'Submit a job' }),
    h('div', { class: 'card' }, drop, fileInput, fileStatus), formBox);

  drop.addEventListener('click', () => fileInput.click());
  drop.addEventListener('keydown', (e) => { if (e.key === 'Enter' || e.key === ' ') { e.preventDefault(); fileInput.click(); } });
  drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
  drop.addEventListener('dragleave', () => drop.classList.remove('over'));
  drop.addEventListener('drop', (e) => { e.preventDefault(); drop.classList.remove('over'); if (e.dataTransfer.files[0]) take(e.dataTransfer.files[0]); });
  fileInput.addEventListener('change', () => { if (fileInput.files[0]) take(fileInput.files[0]); });

  async function take(file) {
    formBox.replaceChildren();
    fileStatus.className = 'small';
    const known = kindOf(file);
    if (!known) {
      fileStatus.className = 'small error';
      fileStatus.textContent = `${file.name}: cannot tell the type from its extension (stl, obj, off, ply, pcd, xyz, each also .gz; png, npy, ngc)`;
      return;
    }
    let [kind, mediaType] = known;
    if (kind === 'ply') kind = await plyKind(file);
    fileStatus.textContent = `Uploading ${file.name} (${fmtBytes(file.size)})…`;
    let art;
    try {
      art = await api('/v1/artifacts', { method: 'POST', headers: { 'content-type': mediaType }, body: file });
    } catch (e) {
      fileStatus.className = 'small error';
      fileStatus.setAttribute('role', 'alert');
      fileStatus.textContent = `${file.name}: ${e.message}`;
      return;
    }
    fileStatus.textContent = `${file.name}: uploaded, ${fmtBytes(art.size)}, sha256 ${art.sha256.slice(0, 12)}…; a ${kind.replace('_', ' ')} starts at the ${FIRST_STAGE[kind]} stage.`;
    formBox.replaceChildren(jobForm(all, catalogs, file, kind, art));
  }
  return root;
}

function jobForm(all, catalogs, file, kind, art) {
  const first = STAGES.indexOf(FIRST_STAGE[kind]);
  const form = h('form', { id: 'job-form', novalidate: true, class: 'card' });
  const name = h('input', { id: 'f-name', type: 'text', value: file.name.replace(/\.[^.]+$/, ''), dataset: { field: 'name', type: 'string' } });
  form.append(h('div', { class: 'fields' },
    h('div', { class: 'field', dataset: { field: 'name' } }, h('label', { for: 'f-name', text: 'name' }), name, h('div', { class: 'field-error', role: 'alert' }))));
  const input = resolve(all, all.JobInput);
  const inputFields = h('div', { class: 'fields' });
  for (const [n, prop] of Object.entries(input.properties || {})) {
    if (n === 'kind' || n === 'artifact') continue;
    if (n === 'units' && kind !== 'mesh' && kind !== 'point_cloud') continue;
    if (['pixel_mm', 'z_min_mm', 'z_max_mm'].includes(n) && kind !== 'depth_map') continue;
    inputFields.append(fieldFor(all, `input.${n}`, n, prop, catalogs));
  }
  if (inputFields.children.length) form.append(h('fieldset', { dataset: { section: 'input' } }, h('legend', { text: 'input' }), inputFields));
  // A mesh may be made by the robot instead of the mill: its own settings, no scan, reconstruct
  // or plan section, of execute only the dexel cell.
  const spec = resolve(all, all.JobSpec || {});
  const robotOk = kind === 'mesh' && all.RobotParams && spec.properties && spec.properties.process;
  let process = null;
  if (robotOk) {
    const box = fieldFor(all, 'process', 'process', spec.properties.process, catalogs);
    process = $('select', box);
    form.append(h('div', { class: 'fields' }, box));
  }
  const bySection = {};
  const sections = [['scan', 'ScanParams'], ['reconstruct', 'ReconstructParams'], ['plan', 'PlanParams'], ['robot', 'RobotParams'], ['execute', 'ExecuteParams']];
  for (const [section, schemaName] of sections) {
    if (section === 'robot' ? !robotOk : STAGES.indexOf(section) < first || !all[schemaName]) continue;
    bySection[section] = h('details', { class: 'section', dataset: { section } }, h('summary', { text: `${section} (optional: defaults when left empty)` }),
      sectionForm(all, section, all[schemaName], catalogs));
    form.append(bySection[section]);
  }
  const applyProcess = () => {
    const robot = process !== null && process.value === 'robot';
    for (const s of ['scan', 'reconstruct', 'plan']) if (bySection[s]) bySection[s].hidden = robot;
    if (bySection.robot) bySection.robot.hidden = !robot;
    if (bySection.execute) {
      for (const f of bySection.execute.querySelectorAll('.field')) f.hidden = robot && f.dataset.field !== 'execute.cell_mm';
      for (const f of bySection.execute.querySelectorAll('fieldset')) f.hidden = robot;
    }
  };
  if (process) process.addEventListener('change', applyProcess);
  applyProcess();
  const general = h('p', { class: 'error', role: 'alert', id: 'form-error' });
  const submit = h('button', { type: 'submit', class: 'primary', id: 'submit-job', text: 'Submit job' });
  form.append(general, h('div', { class: 'row' }, submit, h('span', { class: 'muted small', text: `Input: ${kind.replace('_', ' ')} ${art.sha256.slice(0, 12)}…` })));
  form.addEventListener('submit', async (e) => {
    e.preventDefault();
    general.textContent = '';
    showFieldError(form, null);
    const body = collect(form);
    body.input = { ...(body.input || {}), kind, artifact: art.sha256 };
    submit.disabled = true;
    try {
      const job = await api('/v1/jobs', { method: 'POST', headers: { 'content-type': 'application/json' }, body: JSON.stringify(body) });
      location.hash = `#/jobs/${job.id}`;
    } catch (err) {
      if (!showFieldError(form, err.field, err.message)) general.textContent = err.message;
      submit.disabled = false;
    }
  });
  return form;
}

// ---------------------------------------------------------------- compare

const COMPARE_ROWS = [
  ['cycle_time_s', 'Cycle time (s)', -1], ['cycle_time_no_adaptive_s', 'Cycle time without the adaptive loop (s)', -1],
  ['max_gouge_mm', 'Max gouge (mm)', -1], ['max_leftover_mm', 'Max leftover (mm)', -1], ['rms_deviation_mm', 'RMS deviation (mm)', -1],
  ['part_mean_mm', 'Mean deviation vs original part (mm)', 0], ['part_rms_mm', 'RMS vs original part (mm)', -1],
  ['part_max_gouge_mm', 'Max gouge vs original part (mm)', -1], ['coverage_pct', 'Scan coverage (%)', 1],
];

async function comparePage(params) {
  const page = await api('/v1/jobs?limit=100');
  const jobs = page.jobs;
  const pick = (id, key) => h('select', { id: `compare-${key}`, 'aria-label': `Job ${key.toUpperCase()}` },
    h('option', { value: '', text: '(choose a job)' }),
    jobs.map((j) => h('option', { value: j.id, selected: j.id === id, text: `${j.name || '(unnamed)'} · ${j.status} · ${j.id.slice(0, 8)}` })));
  const a = pick(params.get('a'), 'a'), b = pick(params.get('b'), 'b');
  const go = () => { location.hash = `#/compare?a=${a.value}&b=${b.value}`; };
  a.addEventListener('change', go);
  b.addEventListener('change', go);
  const root = h('section', { 'aria-labelledby': 'compare-title' }, h('h2', { id: 'compare-title', text: 'Compare two jobs' }),
    h('div', { class: 'card row' }, h('label', { for: 'compare-a', text: 'A' }), a, h('label', { for: 'compare-b', text: 'B' }), b));
  if (!a.value || !b.value) return root;
  const [ja, jb] = await Promise.all([api(`/v1/jobs/${a.value}`), api(`/v1/jobs/${b.value}`)]);
  const policy = (j) => (j.spec.execute && j.spec.execute.adaptive) || (j.spec.execute ? 'aco' : '');
  const rows = [
    h('tr', {}, h('th', { scope: 'row', text: 'Status' }), h('td', {}, badge(ja.status)), h('td', {}, badge(jb.status)), h('td')),
    h('tr', {}, h('th', { scope: 'row', text: 'Adaptive policy' }), h('td', { text: policy(ja) }), h('td', { text: policy(jb) }), h('td')),
    h('tr', {}, h('th', { scope: 'row', text: 'Total time' }), h('td', { class: 'num', text: fmtDuration(jobDuration(ja)) }), h('td', { class: 'num', text: fmtDuration(jobDuration(jb)) }), h('td')),
  ];
  const seen = new Set();
  const metricRow = (key, label, better) => {
    seen.add(key);
    const va = ja.metrics?.[key], vb = jb.metrics?.[key];
    if (va === undefined && vb === undefined) return null;
    let diff = '', cls = 'diff';
    if (typeof va === 'number' && typeof vb === 'number') {
      const d = vb - va;
      diff = `${d >= 0 ? '+' : ''}${fmtNum(d)}${va ? ` (${d >= 0 ? '+' : ''}${(100 * d / Math.abs(va)).toFixed(1)} %)` : ''}`;
      if (better && d !== 0) cls += (Math.sign(d) === better) ? ' better' : ' worse';
    }
    return h('tr', { dataset: { metric: key } }, h('th', { scope: 'row', text: label }), h('td', { class: 'num', text: fmtNum(va ?? '') }), h('td', { class: 'num', text: fmtNum(vb ?? '') }), h('td', { class: `num ${cls}`, text: diff }));
  };
  for (const [k, label, better] of COMPARE_ROWS) rows.push(metricRow(k, label, better));
  const others = new Set([...Object.keys(ja.metrics || {}), ...Object.keys(jb.metrics || {})]);
  for (const k of [...others].sort()) if (!seen.has(k)) rows.push(metricRow(k, k, 0));
  root.append(h('div', { class: 'table-wrap' }, h('table', { id: 'compare-table' },
    h('thead', {}, h('tr', {}, h('th', { scope: 'col', text: '' }), h('th', { scope: 'col' }, h('a', { href: `#/jobs/${ja.id}` }, `A: ${ja.name || ja.id.slice(0, 8)}`)),
      h('th', { scope: 'col' }, h('a', { href: `#/jobs/${jb.id}` }, `B: ${jb.name || jb.id.slice(0, 8)}`)), h('th', { scope: 'col', class: 'num', text: 'B − A' }))),
    h('tbody', {}, rows))));
  return root;
}

// ---------------------------------------------------------------- start

$('#token-button').hidden = !sessionStorage.getItem(TOKEN_KEY);
$('#token-button').addEventListener('click', () => { sessionStorage.removeItem(TOKEN_KEY); askToken('Enter a new token.').then(route); });
window.addEventListener('hashchange', route);
route();
