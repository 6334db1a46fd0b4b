// gs360d dashboard: plain ES2020, no framework, no build step. Served by gs360d under a strict
// Content-Security-Policy (no inline script or style): everything the page does is here.
'use strict';

(() => {
  const API = '/api/v1';
  const TOKEN_KEY = 'gs360d.token';
  const ACTIVE = new Set(['running', 'starting']);
  const TERMINAL = new Set(['done', 'failed', 'cancelled']);
  const FRAME_EVERY_MS = 3000;
  const POLL_EVERY_MS = 2000;
  const INFO_EVERY_MS = 5000;
  const LOG_KEEP = 200;
  const ERROR_SCALE_MM = 0.1;

  const $ = (id) => document.getElementById(id);

  // '#run=3' selects run 3; '&live=poll' polls instead of opening the event stream (for proxies
  // that buffer server-sent events, and for headless browsers that wait for the network to be
  // idle, which a stream never is).
  const FORCE_POLL = /(?:^#|[#&])live=poll(?:&|$)/.test(location.hash);

  const state = {
    token: readToken(),
    info: null,
    runs: new Map(), // id -> RUN as listed, merged with live progress
    selected: null, // id of the selected run
    run: null, // the selected run's full view
    probes: null, // the selected run's probes
    probesCost: 0, // ms the last probe list took to arrive
    currentIndex: null, // plan index the machine works on (progress events)
    calibration: null,
    live: 'off', // 'stream', 'polling', 'off'
    last: {}, // name -> time (ms) of the last refresh
    busy: new Set(), // refreshes in flight
    mapPoints: [], // screen positions of the probe map, for the hover read-out
    errorPoints: [],
  };

  // ---- small helpers -------------------------------------------------------------------------

  function readToken() {
    try {
      return sessionStorage.getItem(TOKEN_KEY) || '';
    } catch (e) {
      return '';
    }
  }

  function withToken(url) {
    if (!state.token) return url;
    return url + (url.includes('?') ? '&' : '?') + 'token=' + encodeURIComponent(state.token);
  }

  function setText(id, text) {
    const el = typeof id === 'string' ? $(id) : id;
    const value = text === null || text === undefined ? '' : String(text);
    if (el && el.textContent !== value) el.textContent = value;
  }

  function show(id, visible) {
    const el = typeof id === 'string' ? $(id) : id;
    if (el) el.hidden = !visible;
  }

  function css(name) {
    return getComputedStyle(document.documentElement).getPropertyValue(name).trim() || '#888';
  }

  const pad2 = (n) => String(n).padStart(2, '0');

  // 42s, 4m 05s, 1h 02m
  function fmtDuration(s) {
    if (s === null || s === undefined || !Number.isFinite(s) || s < 0) return '–';
    const t = Math.round(s);
    if (t < 60) return `${t}s`;
    if (t < 3600) return `${Math.floor(t / 60)}m ${pad2(t % 60)}s`;
    const m = Math.round(s / 60);
    return `${Math.floor(m / 60)}h ${pad2(m % 60)}m`;
  }

  function fmtSeconds(s) {
    if (s === null || s === undefined || !Number.isFinite(s)) return '';
    if (s < 1) return `${Math.round(s * 1000)} ms`;
    if (s < 10) return `${s.toFixed(1)} s`;
    return fmtDuration(s);
  }

  function fmtInt(n) {
    return Number.isFinite(n) ? Math.round(n).toLocaleString('en-US') : '–';
  }

  function fmtNum(v) {
    if (v === null || v === undefined || !Number.isFinite(v)) return '–';
    const a = Math.abs(v);
    if (a === 0) return '0';
    if (a >= 100) return v.toFixed(0);
    if (a >= 10) return v.toFixed(1);
    return String(Number(v.toPrecision(3)));
  }

  function clock(d) {
    return `${pad2(d.getHours())}:${pad2(d.getMinutes())}:${pad2(d.getSeconds())}`;
  }

  function fmtTime(unix) {
    if (!unix) return '';
    const d = new Date(unix * 1000);
    const today = new Date();
    const time = `${pad2(d.getHours())}:${pad2(d.getMinutes())}`;
    if (d.toDateString() === today.toDateString()) return time;
    return `${d.getFullYear()}-${pad2(d.getMonth() + 1)}-${pad2(d.getDate())} ${time}`;
  }

  function fmtPosition(p) {
    if (!Array.isArray(p) || p.length < 3) return '–';
    return p.map((v) => (Number.isFinite(v) ? v.toFixed(3) : '?')).join(', ');
  }

  function percent(done, total) {
    if (!total || total <= 0) return 0;
    return Math.max(0, Math.min(100, (100 * done) / total));
  }

  // ---- notices ---------------------------------------------------------------------------------

  let noticeTimer = null;
  function notice(text, kind = 'error') {
    setText('notice-text', text);
    $('notice').dataset.kind = kind;
    show('notice', true);
    clearTimeout(noticeTimer);
    if (kind !== 'error') noticeTimer = setTimeout(() => show('notice', false), 5000);
  }

  // ---- the API -----------------------------------------------------------------------------

  class ApiError extends Error {
    constructor(status, code, message, body) {
      super(message);
      this.status = status;
      this.code = code;
      this.body = body;
    }
  }

  async function api(path, { method = 'GET', body } = {}) {
    const headers = { Accept: 'application/json' };
    if (state.token) headers.Authorization = `Bearer ${state.token}`;
    const init = { method, headers, cache: 'no-store' };
    if (method === 'POST') {
      headers['Content-Type'] = 'application/json';
      init.body = JSON.stringify(body || {});
    }
    let res;
    try {
      res = await fetch(API + path, init);
    } catch (e) {
      setDaemonDown();
      throw new ApiError(0, 'network', 'the daemon does not answer', null);
    }
    const text = await res.text();
    let data = null;
    if (text) {
      try {
        data = JSON.parse(text);
      } catch (e) {
        data = null;
      }
    }
    if (res.status === 401) {
      const message = (data && data.error && data.error.message) || 'this daemon needs a token';
      askToken(message);
      throw new ApiError(401, 'unauthorized', message, data);
    }
    if (!res.ok) {
      const err = (data && data.error) || {};
      throw new ApiError(res.status, err.code || `http_${res.status}`,
        err.message || `${res.status} ${res.statusText}`, data);
    }
    return data;
  }

  // Runs a refresh unless the same one (for the same run) is in flight; records when it last ran.
  async function once(name, fn) {
    const key = `${name}:${state.selected}`;
    if (state.busy.has(key)) return;
    state.busy.add(key);
    state.last[name] = Date.now();
    try {
      await fn();
    } catch (e) {
      if (!(e instanceof ApiError) || (e.status !== 401 && e.status !== 0)) {
        console.warn(name, e);
      }
    } finally {
      state.busy.delete(key);
    }
  }

  // ---- token -----------------------------------------------------------------------------------

  function askToken(message) {
    setText('auth-reason', message.startsWith('wrong')
      ? 'The token was refused; enter it again.'
      : 'This daemon needs an access token.');
    if ($('auth').hidden) {
      show('auth', true);
      $('auth-token').focus();
    }
    setLive('off');
  }

  $('auth-form').addEventListener('submit', (ev) => {
    ev.preventDefault();
    const token = $('auth-token').value.trim();
    if (!token) return;
    state.token = token;
    try {
      sessionStorage.setItem(TOKEN_KEY, token);
    } catch (e) {
      // Private mode: the token lives in memory only.
    }
    $('auth-token').value = '';
    show('auth', false);
    connectEvents();
    refreshAll();
  });

  // ---- header ------------------------------------------------------------------------------------

  function setDaemonDown() {
    setText('daemon-status', 'the daemon does not answer');
    $('daemon-status').dataset.kind = 'error';
  }

  function renderInfo() {
    const info = state.info;
    if (!info) return;
    setText('daemon-status', info.status || 'idle');
    delete $('daemon-status').dataset.kind;
    setText('daemon-version', info.version ? `v${info.version}` : '');
    const m = info.machine || {};
    let machine = 'not configured';
    if (m.configured) machine = m.connected ? (m.state || 'connected') : 'disconnected';
    setText('header-machine', machine);
    $('header-machine').dataset.state = String(machine).toLowerCase().split(':')[0];
    renderActions();
  }

  function setLive(mode) {
    state.live = mode;
    const el = $('live');
    el.dataset.mode = mode;
    el.title = mode === 'stream' ? 'Live updates: the event stream is open'
      : mode === 'polling' ? 'The event stream is not available: polling every 2 s'
        : 'Not connected';
    setText(el, mode === 'stream' ? 'live' : mode === 'polling' ? 'polling' : 'offline');
  }

  // ---- refreshes ---------------------------------------------------------------------------------

  function refreshInfo() {
    return once('info', async () => {
      state.info = await api('/info');
      renderInfo();
    });
  }

  // Fields that change while a run goes on. The list (GET /runs), the run (GET /runs/{id}) and the
  // events all update them: whatever was asked for last wins, so that the list and the run
  // shown (one object) never disagree and an answer that arrives late does not go back in time.
  const LIVE_FIELDS = new Set(['state', 'probes_done', 'probes_total', 'probes_failed',
    'probes_skipped', 'probes_pending', 'elapsed_s', 'eta_s', 'rate_per_h', 'phase',
    'machine_state', 'machine_position', 'last_error', 'awaiting', 'updated_at', 'started_at',
    'finished_at']);

  function mergeRun(r, issued, fromList) {
    let run = state.runs.get(r.id);
    if (!run) {
      run = { _issued: 0 };
      state.runs.set(r.id, run);
    }
    const fresh = issued >= run._issued;
    for (const [key, value] of Object.entries(r)) {
      if (!LIVE_FIELDS.has(key)) {
        run[key] = value;
      } else if (fresh) {
        // The list leaves out the plan's estimate of what is left of a run at rest.
        if (fromList && key === 'eta_s' && value === null && !TERMINAL.has(r.state)) continue;
        run[key] = value;
      }
    }
    if (fresh) run._issued = issued;
    if (fresh && 'state' in r) noteState(r.id, run.state, false);
    return run;
  }

  // ---- browser notifications -------------------------------------------------------------------
  // On request (the header's "notify" chip) the page raises a system notification when a run it
  // saw running ends (done, failed, cancelled, interrupted) and when the machine raises an alarm:
  // a tab left open in the background then tells its user. The choice is kept by the browser.
  const NOTIFY_KEY = 'gs360d.notify';
  const ENDED = new Set(['done', 'failed', 'cancelled', 'interrupted']);
  const notify = {
    seen: new Set(), // runs whose state the page knows
    active: new Set(), // runs seen active, whose end is to be told
    told: new Set(), // runs whose final end (done, failed, cancelled) was told
    alarmed: new Map(), // run -> time of its alarm
  };
  const ALARM_WAIT_MS = 3000;

  function notifySupported() {
    return typeof Notification === 'function';
  }

  function notifyOn() {
    return notifySupported() && Notification.permission === 'granted' &&
      localStorage.getItem(NOTIFY_KEY) === '1';
  }

  function renderNotifyToggle() {
    const button = $('notify-toggle');
    let text = 'off';
    let title = 'Notify me when a run ends or the machine raises an alarm';
    if (!notifySupported() || !window.isSecureContext) {
      text = 'n/a';
      title = notifySupported()
        ? 'Browsers notify only from https:// pages or http://127.0.0.1 (an SSH tunnel does)'
        : 'This browser has no notifications';
      button.disabled = true;
    } else if (Notification.permission === 'denied') {
      text = 'blocked';
      title = 'Notifications are blocked for this site: allow them in the browser\'s settings';
    } else if (notifyOn()) {
      text = 'on';
      title = 'Notifications on (a run ends, an alarm): click to turn them off';
    }
    setText('notify-state', text);
    button.title = title;
    button.dataset.state = text;
    button.setAttribute('aria-pressed', String(text === 'on'));
  }

  $('notify-toggle').addEventListener('click', async () => {
    if (notifyOn()) {
      localStorage.setItem(NOTIFY_KEY, '0');
    } else {
      let permission = Notification.permission;
      if (permission === 'default') permission = await Notification.requestPermission();
      localStorage.setItem(NOTIFY_KEY, permission === 'granted' ? '1' : '0');
    }
    renderNotifyToggle();
  });

  function runLabel(id) {
    const r = state.runs.get(id);
    return r && r.name ? `gs360 run ${id} (${r.name})` : `gs360 run ${id}`;
  }

  function raise(id, what, body) {
    if (!notifyOn()) return;
    try {
      const n = new Notification(`${runLabel(id)}: ${what}`,
        { body, tag: `gs360-run-${id}`, icon: '/icon.svg' });
      n.onclick = () => {
        window.focus();
        if (id !== null) select(id);
        n.close();
      };
    } catch (e) {
      // Some browsers (Chrome on Android) let only a service worker notify: nothing to do.
    }
  }

  // Called with every state the page learns of, from an event or from the list or a run's view:
  // the end of a run seen active is told once; an interruption that follows an alarm is not told
  // again. While the event stream is live, it alone tells the changes, in order: a listing that
  // crossed it (a run's `running` answered after its `done` event) only says what was active when
  // the page first saw the run.
  function noteState(id, s, fromEvent) {
    if (!fromEvent && state.live === 'stream') {
      if (!notify.seen.has(id) && ACTIVE.has(s)) notify.active.add(id);
      notify.seen.add(id);
      return;
    }
    notify.seen.add(id);
    if (ACTIVE.has(s)) {
      notify.active.add(id);
      notify.alarmed.delete(id);
      return;
    }
    if (!ENDED.has(s) || !notify.active.delete(id) || notify.told.has(id)) return;
    if (TERMINAL.has(s)) notify.told.add(id);
    const tell = () => {
      if (s === 'interrupted' && notify.alarmed.has(id)) return;
      const r = state.runs.get(id) || {};
      const parts = [];
      if (r.probes_total) parts.push(`${fmtInt(r.probes_done || 0)} of ${fmtInt(r.probes_total)} probes`);
      if (s !== 'done' && r.last_error) parts.push(r.last_error);
      raise(id, s, parts.join('\n'));
    };
    // The alarm that caused an interruption may reach the page just after it: wait for it.
    if (s === 'interrupted') setTimeout(tell, ALARM_WAIT_MS);
    else tell();
  }

  function onAlarm(d) {
    onLog(d);
    if (d.run === null || d.run === undefined) return;
    // One incident is logged in a few lines that each name the alarm.
    const last = notify.alarmed.get(d.run);
    if (last !== undefined && Date.now() - last < 30000) return;
    notify.alarmed.set(d.run, Date.now());
    raise(d.run, 'machine alarm', d.message || '');
  }

  function refreshRuns() {
    return once('runs', async () => {
      const issued = Date.now();
      const data = await api('/runs');
      const seen = new Set();
      for (const r of data.runs || []) {
        seen.add(r.id);
        mergeRun(r, issued, true);
      }
      for (const id of [...state.runs.keys()]) if (!seen.has(id)) state.runs.delete(id);
      renderRuns();
      if (state.selected !== null && state.runs.has(state.selected)) {
        state.run = state.runs.get(state.selected);
        renderRun();
      }
      if (state.selected === null) autoSelect();
    });
  }

  function refreshRun() {
    const id = state.selected;
    if (id === null) return Promise.resolve();
    return once('run', async () => {
      try {
        const issued = Date.now();
        const run = await api(`/runs/${id}`);
        if (id !== state.selected) return;
        const before = state.run && state.run.id === id ? state.run.state : null;
        state.run = mergeRun(run, issued, false);
        if (before && before !== state.run.state) {
          // The run started, stopped or ended (polling sees it here, the stream in onState).
          refreshProbes();
          refreshFrame();
          refreshLog();
        }
      } catch (e) {
        if (e.status === 404 && id === state.selected) {
          state.run = null;
          state.runs.delete(id);
          renderRuns();
          setText('no-selection', `There is no run ${id}. Select a run.`);
        }
        throw e;
      } finally {
        renderRun();
      }
      renderRunItem(id);
    });
  }

  function refreshProbes() {
    const id = state.selected;
    if (id === null) return Promise.resolve();
    return once('probes', async () => {
      const t0 = performance.now();
      const data = await api(`/runs/${id}/probes`);
      state.probesCost = performance.now() - t0;
      if (id !== state.selected) return;
      state.probes = data.probes || [];
      drawProbeMap();
      drawErrorMap();
    });
  }

  function refreshCalibration() {
    const id = state.selected;
    if (id === null) return Promise.resolve();
    return once('calibration', async () => {
      const data = await api(`/runs/${id}/calibration`);
      if (id !== state.selected) return;
      state.calibration = data;
      renderCalibration();
      renderActions();
    });
  }

  function refreshLog() {
    const id = state.selected;
    if (id === null) return Promise.resolve();
    return once('log', async () => {
      let after = 0;
      let entries = [];
      for (let page = 0; page < 20; page++) {
        const data = await api(`/runs/${id}/log?after=${after}`);
        const events = data.events || [];
        entries = entries.concat(events).slice(-LOG_KEEP);
        if (events.length < 1000) break;
        after = events[events.length - 1].id;
      }
      if (id !== state.selected) return;
      const list = $('log');
      list.replaceChildren();
      for (const e of entries) addLog(e);
      show('log-card', entries.length > 0);
    });
  }

  // The latest frame: loaded into a new <img> that replaces the shown one once it has arrived, so
  // the picture never flickers; the query string defeats every cache on the way.
  function refreshFrame() {
    const id = state.selected;
    if (id === null) return Promise.resolve();
    return once('frame', () => new Promise((resolve) => {
      const img = new Image();
      img.alt = 'Latest camera frame of the run';
      img.decoding = 'async';
      img.onload = () => {
        if (id === state.selected) {
          img.id = 'frame';
          $('frame').replaceWith(img);
          show('frame-empty', false);
          setText('frame-time', `updated ${clock(new Date())}`);
        }
        resolve();
      };
      img.onerror = () => {
        if (id === state.selected && $('frame').hidden) show('frame-empty', true);
        resolve();
      };
      img.src = withToken(`${API}/runs/${id}/frames/latest.png?t=${Date.now()}`);
    }));
  }

  function refreshAll() {
    refreshInfo();
    refreshRuns();
    if (state.selected !== null) {
      refreshRun();
      refreshProbes();
      refreshFrame();
      refreshCalibration();
      refreshLog();
    }
  }

  // ---- selection ---------------------------------------------------------------------------------

  function hashRun() {
    const m = /(?:^#|[#&])run=(\d+)/.exec(location.hash);
    return m ? Number(m[1]) : null;
  }

  function autoSelect() {
    if (state.selected !== null || state.runs.size === 0) return;
    const active = state.info && state.info.active_run;
    const id = active && state.runs.has(active) ? active : Math.max(...state.runs.keys());
    history.replaceState(null, '', `#run=${id}${FORCE_POLL ? '&live=poll' : ''}`);
    select(id);
  }

  function select(id) {
    if (id === state.selected) return;
    state.selected = id;
    state.run = state.runs.get(id) || null;
    state.probes = null;
    state.probesCost = 0;
    state.calibration = null;
    state.currentIndex = null;
    state.mapPoints = [];
    state.errorPoints = [];
    const frame = $('frame');
    frame.hidden = true;
    frame.removeAttribute('src');
    show('frame-empty', true);
    setText('frame-time', '');
    $('log').replaceChildren();
    show('log-card', false);
    renderRuns();
    renderRun();
    renderCalibration();
    drawProbeMap();
    if (id === null) return;
    refreshRun();
    refreshProbes();
    refreshFrame();
    refreshCalibration();
    refreshLog();
  }

  window.addEventListener('hashchange', () => {
    const id = hashRun();
    if (id !== null) select(id);
  });

  // ---- the runs list -----------------------------------------------------------------------------

  function renderRuns() {
    const list = $('runs');
    const ids = [...state.runs.keys()].sort((a, b) => b - a);
    const items = new Map([...list.children].map((li) => [Number(li.dataset.id), li]));
    for (const [id, li] of items) if (!state.runs.has(id)) li.remove();
    let previous = null;
    for (const id of ids) {
      let li = items.get(id);
      if (!li) li = makeRunItem(id);
      const want = previous ? previous.nextSibling : list.firstChild;
      if (li !== want) list.insertBefore(li, want);
      previous = li;
      renderRunItem(id);
    }
    show('runs-empty', ids.length === 0);
  }

  function makeRunItem(id) {
    const li = document.createElement('li');
    li.dataset.id = String(id);
    const a = document.createElement('a');
    a.href = `#run=${id}`;
    a.className = 'run-item';
    const line = document.createElement('span');
    line.className = 'run-line';
    const rid = document.createElement('span');
    rid.className = 'rid';
    const name = document.createElement('span');
    name.className = 'rname';
    const badge = document.createElement('span');
    badge.className = 'badge';
    line.append(rid, name, badge);
    const bar = document.createElement('span');
    bar.className = 'mini-bar';
    const fill = document.createElement('span');
    bar.append(fill);
    const sub = document.createElement('span');
    sub.className = 'run-sub';
    a.append(line, bar, sub);
    li.append(a);
    return li;
  }

  function renderRunItem(id) {
    const li = $('runs').querySelector(`li[data-id="${id}"]`);
    const r = state.runs.get(id);
    if (!li || !r) return;
    const a = li.firstChild;
    const [line, bar, sub] = a.children;
    const [rid, name, badge] = line.children;
    setText(rid, `#${r.id}`);
    setText(name, r.name);
    name.title = r.name;
    setText(badge, r.state);
    badge.dataset.state = r.state;
    const pct = percent(r.probes_done, r.probes_total);
    bar.firstChild.style.width = `${pct.toFixed(1)}%`;
    const parts = [`${r.probes_done} / ${r.probes_total}`, `${Math.floor(pct)}%`];
    if (ACTIVE.has(r.state) && Number.isFinite(r.eta_s)) parts.push(`ETA ${fmtDuration(r.eta_s)}`);
    else if (r.created_at) parts.push(fmtTime(r.created_at));
    setText(sub, parts.join(' · '));
    if (id === state.selected) a.setAttribute('aria-current', 'true');
    else a.removeAttribute('aria-current');
  }

  // ---- the selected run ----------------------------------------------------------------------------

  function renderRun() {
    const r = state.run;
    show('no-selection', !r);
    show('run', !!r);
    show('views', !!r);
    if (!r) {
      show('calibration', false);
      return;
    }
    setText('run-id', `#${r.id}`);
    setText('run-name', r.name);
    setText('run-state', r.state);
    $('run-state').dataset.state = r.state;
    renderProgress(r);
    const err = r.last_error;
    // A run that waits for the user says what to check; the start / resume button answers it.
    setText('run-last-error', !err ? ''
      : r.awaiting ? `Waiting for you to confirm the ${r.awaiting}: ${err}` : `Last error: ${err}`);
    $('run-last-error').dataset.awaiting = r.awaiting || '';
    show('run-last-error', !!err);
    const times = [];
    if (r.created_at) times.push(`created ${fmtTime(r.created_at)}`);
    if (r.started_at) times.push(`started ${fmtTime(r.started_at)}`);
    if (r.finished_at) times.push(`finished ${fmtTime(r.finished_at)}`);
    if (r.shape) times.push(`shape ${r.shape}`);
    if (Number.isFinite(r.candidates)) times.push(`${r.candidates} candidates`);
    setText('run-times', times.join(' · '));
    renderConvergence(r.convergence);
    renderActions();
  }

  // A run that converges: its state, the verdict and one row per checkpoint.
  function renderConvergence(c) {
    show('convergence', !!c);
    if (!c) return;
    setText('convergence-state', c.state.replace('_', ' '));
    $('convergence-state').dataset.state = c.state;
    setText('convergence-verdict', c.verdict ||
      `Calibrates after each round of ${c.checkpoint_probes} probes.`);
    const body = $('checkpoints').querySelector('tbody');
    body.replaceChildren();
    for (const cp of c.checkpoints || []) {
      const figure = (name) => {
        const t = (cp.targets || []).find((x) => x.name === name);
        return t && Number.isFinite(t.value) ? t.value.toFixed(4) : '–';
      };
      const cells = [String(cp.probes), figure('mean depth error'),
        figure('depth error seen > 50 deg'),
        cp.state !== 'done' ? `failed: ${cp.error}` : cp.targets_met ? 'all met' : 'missed',
        fmtSeconds(cp.seconds)];
      const tr = document.createElement('tr');
      cells.forEach((text, i) => {
        const td = document.createElement('td');
        if (i !== 3) td.className = 'num';
        td.textContent = text;
        tr.append(td);
      });
      body.append(tr);
    }
  }

  function renderProgress(r) {
    const done = Number(r.probes_done) || 0;
    const total = Number(r.probes_total) || 0;
    const failed = Number(r.probes_failed) || 0;
    setText('progress-done', String(done));
    setText('progress-total', String(total));
    const pct = percent(done, total);
    // Rounded down, as in the list: 100% only when every probe is done.
    const shown = pct > 0 && pct < 10 ? (Math.floor(pct * 10) / 10).toFixed(1) : Math.floor(pct);
    setText('progress-percent', `${shown}%`);
    $('progress-fill').style.width = `${pct.toFixed(2)}%`;
    const failedPct = Math.min(100 - pct, percent(failed, total));
    $('progress-failed-fill').style.width = `${failedPct.toFixed(2)}%`;
    $('progress-bar').setAttribute('aria-valuenow', pct.toFixed(0));
    const active = ACTIVE.has(r.state);
    setText('run-rate', Number.isFinite(r.rate_per_h) && r.rate_per_h > 0
      ? `${fmtInt(r.rate_per_h)} /h` : '–');
    let eta = '–';
    let end = '–';
    if (Number.isFinite(r.eta_s) && !TERMINAL.has(r.state)) {
      eta = fmtDuration(r.eta_s);
      if (active) {
        const at = new Date(Date.now() + r.eta_s * 1000);
        end = `${pad2(at.getHours())}:${pad2(at.getMinutes())}`;
        if (at.toDateString() !== new Date().toDateString()) end = `${fmtTime(at.getTime() / 1000)}`;
      } else {
        eta = `≈ ${eta}`; // the plan's estimate of what is left
      }
    } else if (r.finished_at) {
      end = fmtTime(r.finished_at);
    }
    setText('run-eta', eta);
    setText('run-end', end);
    setText('run-end-label', r.finished_at && !active ? 'Ended at' : 'Ends at');
    setText('run-elapsed', fmtDuration(r.elapsed_s));
    setText('run-phase', r.phase || (active ? 'starting' : '–'));
    setText('run-failed', String(failed));
    setText('run-skipped', String(Number(r.probes_skipped) || 0));
    setText('run-machine-state', r.machine_state || (active ? 'connecting…' : 'not connected'));
    $('run-machine-state').dataset.state = String(r.machine_state || '').toLowerCase();
    const hasPosition = Array.isArray(r.machine_position);
    setText('run-machine-position', hasPosition ? fmtPosition(r.machine_position) : '');
    show('run-machine-frame', hasPosition);
  }

  function renderActions() {
    const r = state.run;
    const calibrating = (state.calibration && state.calibration.state === 'running') ||
      (r && (r.calibration === 'running' ||
        (state.info && state.info.calibrating_run === r.id)));
    const otherCalibrating = state.info && state.info.calibrating_run &&
      (!r || state.info.calibrating_run !== r.id);
    const s = r ? r.state : '';
    const active = ACTIVE.has(s);
    const enabled = {
      start: s === 'created',
      pause: active,
      resume: s === 'paused' || s === 'interrupted',
      cancel: !!r && !TERMINAL.has(s),
      calibrate: !!r && !active && (r.probes_done || 0) > 0 && !calibrating && !otherCalibrating,
      delete: !!r && !active && !calibrating,
    };
    for (const b of $('actions').querySelectorAll('button[data-action]')) {
      const action = b.dataset.action;
      b.disabled = !enabled[action];
      if (!b.dataset.label) b.dataset.label = b.textContent;
      const asks = !!(r && r.awaiting) && (action === 'start' || action === 'resume');
      b.textContent = asks ? `Confirm ${r.awaiting} & ${action}` : b.dataset.label;
      b.classList.toggle('asks', asks && !b.disabled);
    }
  }

  // ---- actions ----------------------------------------------------------------------------------

  const CONFIRM = {
    cancel: (r) => `Cancel run #${r.id} “${r.name}”? The current probe is finished, the tool ` +
      'parked and the run ends; its data is kept.',
    delete: (r) => `Delete run #${r.id} “${r.name}”? Its probes, frames, log and calibration ` +
      'are removed for good.',
    start: (r) => confirmAwaiting(r, 'start'),
    resume: (r) => confirmAwaiting(r, 'resume'),
  };

  // Null when the run waits for nothing: start / resume then need no confirmation.
  function confirmAwaiting(r, action) {
    if (!r.awaiting) return null;
    const what = r.awaiting === 'position'
      ? 'the tool is clear of the sensor (with homing) or the controller\'s position is true'
      : 'the sensor sits exactly as it did';
    return `${r.last_error || ''}\n\nHave you checked that ${what}? Run #${r.id} will ${action}.`;
  }

  function confirmAction(text) {
    const dialog = $('confirm');
    if (typeof dialog.showModal !== 'function') return Promise.resolve(window.confirm(text));
    setText('confirm-text', text);
    dialog.returnValue = '';
    return new Promise((resolve) => {
      dialog.addEventListener('close', () => resolve(dialog.returnValue === 'yes'), { once: true });
      dialog.showModal();
      $('confirm-yes').focus();
    });
  }

  $('actions').addEventListener('click', async (ev) => {
    const button = ev.target.closest('button[data-action]');
    if (!button || button.disabled || !state.run) return;
    const action = button.dataset.action;
    const run = state.run;
    const question = CONFIRM[action] ? CONFIRM[action](run) : null;
    if (question && !(await confirmAction(question))) return;
    button.disabled = true;
    try {
      if (action === 'delete') {
        await api(`/runs/${run.id}`, { method: 'DELETE' });
        notice(`Run #${run.id} deleted.`, 'info');
        state.runs.delete(run.id);
        state.selected = null;
        state.run = null;
        history.replaceState(null, '', location.pathname);
        renderRuns();
        renderRun();
        autoSelect();
      } else {
        const answers = run.awaiting && (action === 'start' || action === 'resume');
        const body = answers ? { confirm: run.awaiting } : {};
        const res = await api(`/runs/${run.id}/${action}`, { method: 'POST', body });
        notice(`Run #${run.id}: ${(res && res.message) || action}`, 'info');
      }
    } catch (e) {
      if (e.status !== 401) {
        const current = e.body && e.body.state ? ` (the run is ${e.body.state})` : '';
        notice(`${action} refused: ${e.message}${current}`);
      }
    } finally {
      refreshRun();
      refreshRuns();
      refreshInfo();
      if (action === 'calibrate') refreshCalibration();
      renderActions();
    }
  });

  $('notice-close').addEventListener('click', () => show('notice', false));

  // ---- new run ----------------------------------------------------------------------------------

  $('new-run-toggle').addEventListener('click', () => {
    const form = $('new-run-form');
    form.hidden = !form.hidden;
    $('new-run-toggle').setAttribute('aria-expanded', String(!form.hidden));
    if (!form.hidden) $('new-run-name').focus();
  });

  function newRunBody() {
    const body = {};
    const name = $('new-run-name').value.trim();
    if (name) body.name = name;
    const shape = $('new-run-shape').value;
    if (shape) body.shape = { type: shape };
    const probes = $('new-run-probes').value;
    if (probes) body.probes = Number(probes);
    return body;
  }

  function planSummary(plan) {
    if (!plan) return '';
    const parts = [`${plan.probes_total} probes of ${plan.candidates} candidates`];
    if (Number.isFinite(plan.estimate_s)) parts.push(`about ${fmtDuration(plan.estimate_s)}`);
    // Where nothing will be probed, said before the run starts (the largest part; the API's
    // plan lists them all).
    const gaps = Array.isArray(plan.coverage_gaps) ? plan.coverage_gaps : [];
    let text = parts.join(', ');
    if (gaps.length && gaps[0] && typeof gaps[0].text === 'string') {
      text += `. Not probed: ${gaps[0].text}`;
      if (gaps.length > 1) text += ` (and ${gaps.length - 1} smaller part${gaps.length > 2 ? 's' : ''})`;
    }
    return text;
  }

  $('new-run-plan').addEventListener('click', async () => {
    try {
      const plan = await api('/runs', { method: 'POST', body: { ...newRunBody(), plan_only: true } });
      setText('new-run-estimate', planSummary(plan.plan || plan));
    } catch (e) {
      if (e.status !== 401) setText('new-run-estimate', e.message);
    }
  });

  $('new-run-form').addEventListener('submit', async (ev) => {
    ev.preventDefault();
    try {
      const run = await api('/runs', { method: 'POST', body: newRunBody() });
      setText('new-run-estimate', '');
      $('new-run-form').hidden = true;
      $('new-run-toggle').setAttribute('aria-expanded', 'false');
      notice(`Run #${run.id} planned: ${planSummary(run.plan)}.`, 'info');
      mergeRun(run, Date.now(), false);
      location.hash = `run=${run.id}${FORCE_POLL ? '&live=poll' : ''}`;
      refreshRuns();
    } catch (e) {
      if (e.status !== 401) setText('new-run-estimate', e.message);
    }
  });

  // ---- the log ------------------------------------------------------------------------------------

  function addLog(e) {
    const list = $('log');
    const li = document.createElement('li');
    li.dataset.level = e.level || 'info';
    const time = document.createElement('time');
    const d = new Date((e.time || Date.now() / 1000) * 1000);
    time.textContent = clock(d);
    const level = document.createElement('span');
    level.className = 'level';
    level.textContent = e.level || 'info';
    const msg = document.createElement('span');
    msg.className = 'msg';
    msg.textContent = e.message || '';
    li.append(time, level, msg);
    list.prepend(li);
    while (list.children.length > LOG_KEEP) list.lastChild.remove();
    show('log-card', true);
  }

  // ---- calibration ------------------------------------------------------------------------------

  function renderCalibration() {
    const c = state.calibration;
    const r = state.run;
    const has = !!c && !!r && (c.state !== 'none' || (c.stages && c.stages.length > 0));
    show('calibration', has);
    if (!has) return;
    setText('calibration-state', c.state);
    $('calibration-state').dataset.state = c.state;
    show('calibration-error', !!c.error);
    setText('calibration-error', c.error || '');

    const stages = $('stages');
    stages.replaceChildren();
    for (const s of c.stages || []) {
      const li = document.createElement('li');
      li.dataset.state = s.state;
      const name = document.createElement('span');
      name.className = 'stage-name';
      name.textContent = s.name;
      const st = document.createElement('span');
      st.className = 'badge';
      st.dataset.state = s.state;
      st.textContent = s.state;
      const secs = document.createElement('span');
      secs.className = 'stage-secs';
      secs.textContent = s.state === 'pending' ? '' : fmtSeconds(s.seconds);
      li.append(name, st, secs);
      if (s.message) {
        const msg = document.createElement('span');
        msg.className = 'stage-msg';
        msg.textContent = s.message;
        li.append(msg);
      }
      stages.append(li);
    }

    // The calibration's warnings: what missed and what to do about it (more probes, a smaller
    // network), as `gs360 calibrate` prints them.
    const warnings = Array.isArray(c.warnings) ? c.warnings : [];
    const advice = $('calibration-warnings');
    advice.replaceChildren();
    for (const w of warnings) {
      const li = document.createElement('li');
      li.dataset.code = (w && w.code) || '';
      li.textContent = (w && w.message) || String(w);
      advice.append(li);
    }
    show('calibration-warnings', warnings.length > 0);

    const targets = c.targets || [];
    const body = $('targets').tBodies[0];
    body.replaceChildren();
    for (const t of targets) {
      const tr = document.createElement('tr');
      const pass = t.no_data === true ? 'n/a'
        : t.pass === true ? 'pass' : t.pass === false ? 'fail' : 'n/a';
      tr.dataset.result = pass;
      const name = document.createElement('th');
      name.scope = 'row';
      name.textContent = t.name;
      if (t.truth) {
        const truth = document.createElement('span');
        truth.className = 'truth';
        truth.textContent = ` (${t.truth})`;
        name.append(truth);
      }
      const unit = t.unit ? ` ${t.unit}` : '';
      const value = document.createElement('td');
      value.className = 'num';
      value.dataset.label = 'value';
      value.textContent = fmtNum(t.value) + unit;
      const target = document.createElement('td');
      target.className = 'num';
      target.dataset.label = 'target';
      // The figures are bounds from above (errors) unless the verdict says otherwise.
      const atMost = t.pass === null || t.pass === undefined || !Number.isFinite(t.value) ||
        (t.value <= t.target) === (t.pass === true);
      target.textContent = `${atMost ? '≤' : '≥'} ${fmtNum(t.target)}${unit}`;
      const result = document.createElement('td');
      const badge = document.createElement('span');
      badge.className = 'result';
      badge.dataset.result = pass;
      badge.textContent = pass === 'pass' ? '✓ pass' : pass === 'fail' ? '✗ fail'
        : t.no_data === true ? 'no data' : 'n/a';
      result.append(badge);
      tr.append(name, value, target, result);
      body.append(tr);
    }
    const errors = c.validation && Array.isArray(c.validation.probe_errors)
      ? c.validation.probe_errors : [];
    show('validation', targets.length > 0 || errors.length > 0);
    drawErrorMap();

    const done = c.state === 'done';
    show('downloads', done);
    if (done) {
      const base = `${API}/runs/${r.id}`;
      $('dl-report').href = withToken(`${base}/report`);
      $('dl-model').href = withToken(`${base}/model`);
      $('dl-onnx').href = withToken(`${base}/model.onnx`);
      $('dl-validation').href = withToken(`${base}/validation.json`);
    }
  }

  // ---- maps ---------------------------------------------------------------------------------------

  function prepCanvas(canvas, aspect, minH, maxH) {
    const w = Math.max(200, Math.floor(canvas.clientWidth || canvas.parentElement.clientWidth));
    const h = Math.round(Math.min(maxH, Math.max(minH, w * aspect)));
    if (canvas.style.height !== `${h}px`) canvas.style.height = `${h}px`;
    const dpr = window.devicePixelRatio || 1;
    const pw = Math.round(w * dpr);
    const ph = Math.round(h * dpr);
    if (canvas.width !== pw || canvas.height !== ph) {
      canvas.width = pw;
      canvas.height = ph;
    }
    const ctx = canvas.getContext('2d');
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    return { ctx, w, h };
  }

  function niceStep(range, count) {
    const raw = range / count;
    const p = 10 ** Math.floor(Math.log10(raw));
    for (const m of [1, 2, 2.5, 5, 10]) if (raw <= m * p) return m * p;
    return 10 * p;
  }

  function azimuth(p) {
    return (Math.atan2(p[1], p[0]) * 180) / Math.PI;
  }

  function zRange(points) {
    let lo = 0;
    let hi = -Infinity;
    for (const p of points) {
      if (p[2] < lo) lo = p[2];
      if (p[2] > hi) hi = p[2];
    }
    if (!Number.isFinite(hi)) hi = 1;
    if (hi - lo < 1) hi = lo + 1;
    return [lo, hi];
  }

  // Axes of an unrolled map: azimuth (degrees) across, height z (mm) up.
  function drawAxes(ctx, w, h, z0, z1) {
    const m = { l: 44, r: 10, t: 10, b: 24 };
    const pw = w - m.l - m.r;
    const ph = h - m.t - m.b;
    const step = niceStep(z1 - z0, Math.max(2, Math.min(6, Math.floor(ph / 40))));
    const lo = Math.floor(z0 / step) * step;
    const hi = Math.ceil(z1 / step - 1e-9) * step;
    const X = (az) => m.l + ((az + 180) / 360) * pw;
    const Y = (z) => m.t + (1 - (z - lo) / (hi - lo)) * ph;
    ctx.fillStyle = css('--plot-bg');
    ctx.fillRect(m.l, m.t, pw, ph);
    ctx.strokeStyle = css('--grid');
    ctx.lineWidth = 1;
    ctx.fillStyle = css('--muted');
    ctx.font = '11px system-ui, sans-serif';
    ctx.textAlign = 'center';
    ctx.textBaseline = 'top';
    ctx.beginPath();
    for (const az of [-180, -135, -90, -45, 0, 45, 90, 135, 180]) {
      const x = Math.round(X(az)) + 0.5;
      ctx.moveTo(x, m.t);
      ctx.lineTo(x, m.t + ph);
      if (az % 90 === 0 || pw > 520) {
        ctx.textAlign = az === 180 ? 'right' : az === -180 ? 'left' : 'center';
        ctx.fillText(`${az}°`, az === 180 ? x + 4 : az === -180 ? x - 4 : x, m.t + ph + 5);
      }
    }
    ctx.textAlign = 'right';
    ctx.textBaseline = 'middle';
    for (let z = lo; z <= hi + step * 1e-6; z += step) {
      const y = Math.round(Y(z)) + 0.5;
      ctx.moveTo(m.l, y);
      ctx.lineTo(m.l + pw, y);
      ctx.fillText(`${Number(z.toFixed(2))}`, m.l - 6, y);
    }
    ctx.stroke();
    ctx.save();
    ctx.translate(11, m.t + ph / 2);
    ctx.rotate(-Math.PI / 2);
    ctx.textAlign = 'center';
    ctx.fillText('z (mm)', 0, 0);
    ctx.restore();
    return { X, Y, m, pw, ph };
  }

  const PROBE_ORDER = ['planned', 'skipped', 'captured', 'failed'];

  function drawProbeMap() {
    const canvas = $('probe-map');
    if (!canvas || canvas.offsetParent === null) return;
    const probes = state.probes || [];
    const { ctx, w, h } = prepCanvas(canvas, 0.5, 220, 420);
    const pts = probes.map((p) => p.point);
    const [z0, z1] = zRange(pts);
    const ax = drawAxes(ctx, w, h, z0, z1);
    const counts = { captured: 0, failed: 0, skipped: 0, planned: 0 };
    const r = Math.max(1.3, Math.min(4.5, 0.42 * Math.sqrt((ax.pw * ax.ph) / Math.max(1, probes.length))));
    const screen = new Array(probes.length);
    const groups = { captured: [], failed: [], skipped: [], planned: [] };
    probes.forEach((p, i) => {
      const x = ax.X(azimuth(p.point));
      const y = ax.Y(p.point[2]);
      screen[i] = [x, y, i];
      const g = groups[p.state] ? p.state : 'planned';
      counts[g]++;
      groups[g].push(i);
    });
    for (const name of PROBE_ORDER) {
      const list = groups[name];
      if (!list.length) continue;
      ctx.beginPath();
      for (const i of list) {
        const [x, y] = screen[i];
        ctx.moveTo(x + r, y);
        ctx.arc(x, y, r, 0, 2 * Math.PI);
      }
      // Dense maps: the planned points' outlines would cover the map; filled, a shade darker.
      ctx.fillStyle = css(name === 'planned' && r < 2.5 ? '--planned-dense' : `--${name}`);
      ctx.fill();
      if (name === 'planned' && r >= 2.5) {
        ctx.strokeStyle = css('--planned-edge');
        ctx.lineWidth = 0.8;
        ctx.stroke();
      }
    }
    const cur = state.currentIndex;
    if (state.run && ACTIVE.has(state.run.state) && cur !== null) {
      const i = probes.findIndex((p) => p.index === cur);
      if (i >= 0) {
        const [x, y] = screen[i];
        ctx.beginPath();
        ctx.arc(x, y, r + 4, 0, 2 * Math.PI);
        ctx.strokeStyle = css('--accent');
        ctx.lineWidth = 2;
        ctx.stroke();
      }
    }
    state.mapPoints = screen;
    for (const k of Object.keys(counts)) setText(`legend-${k}`, String(counts[k]));
    setText('map-count', probes.length ? `${probes.length} points` : '');
    if (!probes.length) {
      ctx.fillStyle = css('--muted');
      ctx.textAlign = 'center';
      ctx.fillText(state.selected === null ? '' : 'loading…', ax.m.l + ax.pw / 2, ax.m.t + ax.ph / 2);
    }
  }

  const ERROR_STOPS = [
    [0.0, [44, 123, 182]],
    [0.25, [120, 190, 220]],
    [0.5, [250, 220, 90]],
    [0.75, [250, 140, 60]],
    [1.0, [200, 30, 40]],
  ];

  function errorColour(mm) {
    const t = Math.max(0, Math.min(1, (Number(mm) || 0) / ERROR_SCALE_MM));
    for (let i = 1; i < ERROR_STOPS.length; i++) {
      const [t1, c1] = ERROR_STOPS[i];
      if (t <= t1) {
        const [t0, c0] = ERROR_STOPS[i - 1];
        const f = (t - t0) / (t1 - t0);
        const c = c0.map((v, k) => Math.round(v + f * (c1[k] - v)));
        return `rgb(${c[0]}, ${c[1]}, ${c[2]})`;
      }
    }
    return 'rgb(200, 30, 40)';
  }

  function drawErrorScale() {
    const canvas = $('error-scale');
    const ctx = canvas.getContext('2d');
    for (let x = 0; x < canvas.width; x++) {
      ctx.fillStyle = errorColour((x / (canvas.width - 1)) * ERROR_SCALE_MM);
      ctx.fillRect(x, 0, 1, canvas.height);
    }
  }

  function drawErrorMap() {
    const canvas = $('error-map');
    const c = state.calibration;
    const errors = c && c.validation && Array.isArray(c.validation.probe_errors)
      ? c.validation.probe_errors.filter((e) => Array.isArray(e) && e.length >= 4) : [];
    if (!canvas || canvas.offsetParent === null || !errors.length) return;
    const { ctx, w, h } = prepCanvas(canvas, 0.45, 200, 380);
    const ref = state.probes && state.probes.length ? state.probes.map((p) => p.point) : errors;
    const [z0, z1] = zRange(ref.concat(errors));
    const ax = drawAxes(ctx, w, h, z0, z1);
    const r = Math.max(2.5, Math.min(6, 0.5 * Math.sqrt((ax.pw * ax.ph) / errors.length)));
    const screen = [];
    // Largest errors last, so they stay visible where points overlap.
    const order = errors.map((e, i) => i).sort((a, b) => errors[a][3] - errors[b][3]);
    ctx.lineWidth = 0.8;
    ctx.strokeStyle = 'rgba(0, 0, 0, 0.55)';
    for (const i of order) {
      const e = errors[i];
      const x = ax.X(azimuth(e));
      const y = ax.Y(e[2]);
      screen.push([x, y, i]);
      ctx.beginPath();
      ctx.arc(x, y, r, 0, 2 * Math.PI);
      ctx.fillStyle = errorColour(e[3]);
      ctx.fill();
      ctx.stroke();
    }
    state.errorPoints = screen;
  }

  function nearest(points, x, y, limit) {
    let best = null;
    let bestD = limit * limit;
    for (const p of points) {
      const d = (p[0] - x) ** 2 + (p[1] - y) ** 2;
      if (d <= bestD) {
        bestD = d;
        best = p;
      }
    }
    return best;
  }

  function canvasXY(canvas, ev) {
    const rect = canvas.getBoundingClientRect();
    return [ev.clientX - rect.left, ev.clientY - rect.top];
  }

  $('probe-map').addEventListener('mousemove', (ev) => {
    const [x, y] = canvasXY($('probe-map'), ev);
    const hit = nearest(state.mapPoints, x, y, 8);
    if (!hit || !state.probes) return;
    const p = state.probes[hit[2]];
    if (!p) return;
    const extra = p.last_error ? ` — ${p.last_error}` : p.skip_reason ? ` — ${p.skip_reason}` : '';
    setText('map-hover', `probe ${p.index}: ${p.state}, azimuth ${azimuth(p.point).toFixed(1)}°, ` +
      `z ${p.point[2].toFixed(2)} mm, ${p.attempts} attempt${p.attempts === 1 ? '' : 's'}${extra}`);
  });

  $('error-map').addEventListener('mousemove', (ev) => {
    const [x, y] = canvasXY($('error-map'), ev);
    const hit = nearest(state.errorPoints, x, y, 10);
    const c = state.calibration;
    if (!hit || !c || !c.validation) return;
    const e = c.validation.probe_errors[hit[2]];
    setText('error-hover', `azimuth ${azimuth(e).toFixed(1)}°, z ${e[2].toFixed(2)} mm: ` +
      `mean depth error ${fmtNum(e[3])} mm`);
  });

  let resizeTimer = null;
  function redrawMaps() {
    clearTimeout(resizeTimer);
    resizeTimer = setTimeout(() => {
      drawProbeMap();
      drawErrorMap();
    }, 100);
  }
  if (typeof ResizeObserver === 'function') {
    const ro = new ResizeObserver(redrawMaps);
    ro.observe($('probe-map'));
    ro.observe($('error-map'));
  } else {
    window.addEventListener('resize', redrawMaps);
  }

  // ---- live updates --------------------------------------------------------------------------------

  let source = null;
  let reconnectTimer = null;

  function onProgress(d) {
    const r = state.runs.get(d.run);
    const fields = ['probes_done', 'probes_total', 'probes_failed', 'elapsed_s', 'eta_s',
      'rate_per_h', 'phase', 'machine_state', 'machine_position'];
    if (r) {
      for (const f of fields) if (f in d) r[f] = d[f];
      r._issued = Date.now();
      renderRunItem(d.run);
    } else {
      refreshRuns();
    }
    if (state.run && state.run.id === d.run) {
      if ('plan_index' in d) state.currentIndex = d.plan_index;
      renderProgress(state.run);
      renderActions();
    }
    if (state.info && state.info.machine) {
      if (d.machine_state) {
        state.info.machine.connected = true;
        state.info.machine.state = d.machine_state;
      }
      setText('header-machine', state.info.machine.state || 'connected');
      $('header-machine').dataset.state = String(state.info.machine.state || '').toLowerCase();
    }
  }

  function onState(d) {
    if (d.state === 'deleted') {
      state.runs.delete(d.run);
      renderRuns();
      if (state.selected === d.run) {
        state.selected = null;
        state.run = null;
        history.replaceState(null, '', location.pathname);
        renderRun();
        autoSelect();
      }
    } else {
      noteState(d.run, d.state, true);
      const r = state.runs.get(d.run);
      if (r) {
        r.state = d.state;
        r._issued = Date.now();
        renderRunItem(d.run);
      }
      if (state.run && state.run.id === d.run) renderRun();
      refreshRuns();
    }
    if (state.selected === d.run) {
      refreshRun();
      refreshFrame();
      refreshProbes();
    }
    refreshInfo();
  }

  function onRunEnd(d) {
    if (state.selected === d.run) {
      refreshRun();
      refreshProbes();
      refreshFrame();
      if (d.outcome && d.outcome !== 'done' && d.message) {
        notice(`Run #${d.run} ${d.outcome}: ${d.message}`,
          d.outcome === 'failed' || d.state === 'failed' ? 'error' : 'info');
      }
    }
    refreshRuns();
    refreshInfo();
  }

  function onCalibration(d) {
    if (state.selected === d.run) {
      refreshCalibration();
      refreshRun();
      if (d.state === 'failed' && d.error) notice(`Calibration of run #${d.run} failed: ${d.error}`);
    }
    refreshInfo();
  }

  function onLog(d) {
    if (state.selected === d.run) addLog(d);
  }

  let eventCount = 0;

  function parse(handler) {
    return (ev) => {
      if (typeof ev.data !== 'string') return;
      // How many events the page has had: read by the browser test.
      eventCount++;
      $('live').dataset.events = String(eventCount);
      let data = null;
      try {
        data = JSON.parse(ev.data);
      } catch (e) {
        return;
      }
      handler(data);
    };
  }

  // EventSource does not say why it gave up. A daemon with all its event streams open answers
  // 503 (server.max_event_streams): say so in the live badge's title, then close the request.
  async function explainRefusedStream() {
    const ctl = new AbortController();
    try {
      const r = await fetch(withToken(`${API}/events`), { signal: ctl.signal });
      if (r.status === 503 && state.live === 'polling') {
        $('live').title = 'gs360d has as many event streams open as it allows ' +
          '(server.max_event_streams: other tabs or clients): polling every 2 s';
      }
    } catch (e) {
      // Unreachable: the badge already says polling.
    }
    ctl.abort();
  }

  function connectEvents() {
    if (source) source.close();
    source = null;
    clearTimeout(reconnectTimer);
    if (FORCE_POLL || typeof EventSource !== 'function') {
      setLive('polling');
      return;
    }
    const es = new EventSource(withToken(`${API}/events`));
    source = es;
    es.onopen = () => {
      if (source !== es) return;
      const wasDown = state.live !== 'stream';
      setLive('stream');
      // Whatever happened while the stream was down.
      if (wasDown && state.last.runs) refreshAll();
    };
    es.onerror = (ev) => {
      if (source !== es) return;
      // The browser retries by itself (CONNECTING); meanwhile, and for good once it gives up
      // (CLOSED: a 401 or a proxy that does not stream), poll.
      setLive('polling');
      if (es.readyState === EventSource.CLOSED) {
        source = null;
        reconnectTimer = setTimeout(connectEvents, 15000);
        explainRefusedStream();
      }
    };
    es.addEventListener('progress', parse(onProgress));
    es.addEventListener('state', parse(onState));
    es.addEventListener('run_end', parse(onRunEnd));
    es.addEventListener('stage', parse((d) => {
      if (state.selected === d.run) refreshCalibration();
    }));
    es.addEventListener('calibration', parse(onCalibration));
    es.addEventListener('convergence', parse((d) => {
      if (state.selected === d.run) refreshRun();
    }));
    es.addEventListener('alarm', parse(onAlarm));
    for (const type of ['failure', 'warning', 'log']) {
      es.addEventListener(type, parse(onLog));
    }
  }

  // One clock for everything periodic: what is due depends on the state of the selected run.
  function tick() {
    if (!$('auth').hidden) return;
    const now = Date.now();
    const due = (name, every) => now - (state.last[name] || 0) >= every;
    const r = state.run;
    const active = !!r && ACTIVE.has(r.state);
    if (due('info', INFO_EVERY_MS)) refreshInfo();
    if (state.live !== 'stream') {
      if (state.selected !== null && due('run', POLL_EVERY_MS)) refreshRun();
      if (due('runs', INFO_EVERY_MS)) refreshRuns();
      if (active && due('log', 10000)) refreshLog();
    } else if (active && due('run', 15000)) {
      refreshRun(); // fields the events do not carry (last_error, skipped)
    }
    if (active && due('frame', FRAME_EVERY_MS)) refreshFrame();
    if (active) {
      // A big run's list is megabytes of JSON: never spend more than a fifth of the time on it.
      const n = state.probes ? state.probes.length : 0;
      const every = Math.max(n > 5000 ? 10000 : n > 2000 ? 6000 : 4000, 5 * state.probesCost);
      if (due('probes', every)) refreshProbes();
    }
    const calibrating = (state.calibration && state.calibration.state === 'running') ||
      (r && r.calibration === 'running');
    if (calibrating && due('calibration', POLL_EVERY_MS)) refreshCalibration();
  }

  // ---- start -------------------------------------------------------------------------------------

  drawErrorScale();
  renderNotifyToggle();
  setLive('off');
  const initial = hashRun();
  refreshInfo();
  refreshRuns().then(() => {
    if (initial === null) autoSelect();
  });
  if (initial !== null) select(initial);
  connectEvents();
  setInterval(tick, 1000);
})();
