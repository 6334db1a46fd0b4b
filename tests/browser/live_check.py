#!/usr/bin/env python3
"""The dashboard's live path, which a DOM dump cannot see: headless Chromium driven over the
DevTools protocol on a pipe (--remote-debugging-pipe: no port, no extra package).

  live_check.py CHROMIUM PAGE_URL PROFILE_DIR CHROMIUM_LOG
  live_check.py --confirm CHROMIUM PAGE_URL PROFILE_DIR CHROMIUM_LOG
  live_check.py --notify START_URL EXPECT CHROMIUM PAGE_URL PROFILE_DIR CHROMIUM_LOG

1. Opens PAGE_URL (the dashboard with a running run selected, streaming: no live=poll) at
   1280x900 and waits for the header to say "live" (the EventSource is open) and for
   #progress-done to show a number.
2. Leaves the page alone and waits for #progress-done to grow: only the event stream (or the
   polling fallback, which "live" rules out) can change it.
3. Opens the new-run form and asks for an estimate: it must give the probe count and where
   nothing will be probed (the plan's coverage gaps).
4. Narrows the viewport to a phone's (390x844): nothing may be wider than the screen
   (no horizontal scrolling) and the runs list must sit above the run (one column); a
   calibration stage's name in a card narrower than it stays one word on one line.

With --confirm, PAGE_URL shows a run that waits for the user to confirm its position: the page
must say so, its start button must offer to confirm; the check clicks it, answers the dialog with
yes, and waits for the run to leave `created` (the daemon took the confirmation).

With --notify, PAGE_URL shows a run not yet started: the check lets the page notify (the
permission granted as a user would, through the DevTools protocol), turns its "notify" chip on,
reloads (the choice is kept), POSTs START_URL, and waits for the page to raise a system
notification whose title contains EXPECT, and no other (the page's Notification constructor is wrapped
to record what it is given).

Prints what it compares. Exit status 0: passed; 1: a check failed; 2: Chromium or the protocol
failed. Python standard library only.
"""
import json
import os
import select
import subprocess
import sys
import time
import urllib.parse
import urllib.request


class ProtocolError(Exception):
    pass


class Chromium:
    def __init__(self, binary, profile, log_path):
        # Chromium reads commands on fd 3 and writes answers on fd 4, NUL-terminated JSON.
        to_chrome_r, self.to_chrome = os.pipe()
        self.from_chrome, from_chrome_w = os.pipe()

        def fds():
            a, b = os.dup(to_chrome_r), os.dup(from_chrome_w)
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.log = open(log_path, 'ab')
        self.proc = subprocess.Popen(
            [binary, '--headless', '--no-sandbox', '--disable-gpu', '--disable-quic',
             '--no-first-run', '--disable-background-networking', '--disable-component-update',
             '--disable-sync', '--disable-dev-shm-usage', '--no-default-browser-check',
             '--mute-audio', '--password-store=basic', '--hide-scrollbars',
             '--remote-debugging-pipe', f'--user-data-dir={profile}', 'about:blank'],
            stdin=subprocess.DEVNULL, stdout=self.log, stderr=self.log, preexec_fn=fds,
            close_fds=False)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self.buffer = b''
        self.next_id = 0
        self.session = None
        self.events = []  # what the page reported on its own: exceptions, console, log

    def _read(self, deadline):
        while b'\0' not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ProtocolError('Chromium did not answer in time')
            ready, _, _ = select.select([self.from_chrome], [], [], left)
            if not ready:
                continue
            chunk = os.read(self.from_chrome, 1 << 16)
            if not chunk:
                raise ProtocolError('Chromium closed the DevTools pipe')
            self.buffer += chunk
        message, self.buffer = self.buffer.split(b'\0', 1)
        return json.loads(message)

    def send(self, method, params=None, session=True, timeout=20):
        self.next_id += 1
        message = {'id': self.next_id, 'method': method, 'params': params or {}}
        if session and self.session:
            message['sessionId'] = self.session
        os.write(self.to_chrome, json.dumps(message).encode() + b'\0')
        deadline = time.monotonic() + timeout
        while True:
            answer = self._read(deadline)
            if answer.get('id') == self.next_id:
                if 'error' in answer:
                    raise ProtocolError(f'{method}: {answer["error"]}')
                return answer.get('result', {})
            if 'method' in answer:
                self.events.append(answer)

    def open(self, url, width, height, init_script=None):
        target = self.send('Target.createTarget', {'url': 'about:blank'}, session=False)
        self.session = self.send('Target.attachToTarget',
                                 {'targetId': target['targetId'], 'flatten': True},
                                 session=False)['sessionId']
        self.viewport(width, height, mobile=False)
        self.send('Runtime.enable')
        self.send('Log.enable')
        if init_script:
            self.send('Page.enable')
            self.send('Page.addScriptToEvaluateOnNewDocument', {'source': init_script})
        self.send('Page.navigate', {'url': url})

    def problems(self):
        """Uncaught exceptions, console warnings and errors, CSP violations of the page."""
        found = []
        for e in self.events:
            method, params = e.get('method'), e.get('params', {})
            if method == 'Runtime.exceptionThrown':
                details = params.get('exceptionDetails', {})
                text = details.get('exception', {}).get('description') or details.get('text')
                found.append(f'uncaught exception: {text}')
            elif method == 'Runtime.consoleAPICalled' and params.get('type') in ('error', 'warning'):
                args = [a.get('value', a.get('description')) for a in params.get('args', [])]
                found.append(f'console.{params["type"]}: {args}')
            elif method == 'Log.entryAdded':
                entry = params.get('entry', {})
                # Network errors are expected (no frame yet: 404); not script or CSP errors.
                if entry.get('level') == 'error' and entry.get('source') != 'network':
                    found.append(f'{entry.get("source")}: {entry.get("text")}')
        return found

    def viewport(self, width, height, mobile):
        self.send('Emulation.setDeviceMetricsOverride',
                  {'width': width, 'height': height, 'deviceScaleFactor': 1, 'mobile': mobile})

    def eval(self, expression):
        result = self.send('Runtime.evaluate', {'expression': expression, 'returnByValue': True})
        if 'exceptionDetails' in result:
            raise ProtocolError(f'{expression}: {result["exceptionDetails"].get("text")}')
        return result.get('result', {}).get('value')

    def close(self):
        try:
            self.send('Browser.close', session=False, timeout=5)
        except (ProtocolError, OSError):
            pass
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


READ = ('(() => { const t = (id) => { const e = document.getElementById(id); '
        'return e ? e.textContent : null; }; '
        'return {done: t("progress-done"), total: t("progress-total"), live: t("live"), '
        'state: t("run-state"), events: Number((document.getElementById("live") || '
        '{dataset: {}}).dataset.events || 0)}; })()')

LAYOUT = ('(() => { const r = (id) => document.getElementById(id).getBoundingClientRect(); '
          'return {scroll: document.documentElement.scrollWidth, '
          'client: document.documentElement.clientWidth, '
          'sidebarBottom: r("sidebar").bottom, detailTop: r("detail").top, '
          'sidebarWidth: r("sidebar").width, detailWidth: r("detail").width}; })()')

# A stage's name in a card far narrower than the name: how many lines its text takes (a
# Range has one box per line; the name's own element, a grid item, has one in all).
STAGE_NAME_LINES = ('(() => { const ol = document.createElement("ol"); ol.className = "stages"; '
                    'ol.style.width = "60px"; const li = document.createElement("li"); '
                    'const s = document.createElement("span"); s.className = "stage-name"; '
                    's.textContent = "intrinsics"; li.append(s); ol.append(li); '
                    'document.body.append(ol); const r = document.createRange(); '
                    'r.selectNodeContents(s); const n = r.getClientRects().length; ol.remove(); '
                    'return n; })()')


def log(text):
    print(f'live_check: {text}', flush=True)


def wait_for(chrome, what, test, timeout):
    deadline = time.monotonic() + timeout
    seen = None
    while time.monotonic() < deadline:
        seen = chrome.eval(READ)
        if test(seen):
            return seen
        time.sleep(0.25)
    log(f'FAIL: timed out after {timeout} s waiting for {what}; the page shows {seen}')
    sys.exit(1)


ASKS = ('(() => { const e = (id) => document.getElementById(id); '
        'const b = document.querySelector("button[data-action=start]"); '
        'const err = e("run-last-error"); const st = e("run-state"); '
        'return {error: !err || err.hidden ? "" : err.textContent, '
        'state: st ? st.textContent : "", button: b ? b.textContent : null, '
        'enabled: b ? !b.disabled : false}; })()')


def confirm_check(chrome, url):
    chrome.open(url, 1280, 900)
    deadline = time.monotonic() + 30
    seen = None
    while time.monotonic() < deadline:
        seen = chrome.eval(ASKS)
        if 'Waiting for you to confirm the position' in seen['error'] and seen['enabled']:
            break
        time.sleep(0.25)
    else:
        log(f'FAIL: the page does not say the run waits for a confirmation: {seen}')
        return 1
    log(f'the page asks: "{seen["error"][:90]}..."; button: "{seen["button"]}"')
    if seen['button'] != 'Confirm position & start':
        log(f'FAIL: the start button says "{seen["button"]}"')
        return 1
    chrome.eval('document.querySelector("button[data-action=start]").click()')
    time.sleep(0.5)
    question = chrome.eval('document.getElementById("confirm").open ? '
                           'document.getElementById("confirm-text").textContent : null')
    if not question or 'Have you checked' not in question:
        log(f'FAIL: no confirmation dialog after the click: {question}')
        return 1
    chrome.eval('document.getElementById("confirm-yes").click()')
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        seen = chrome.eval(ASKS)
        if seen['state'] not in ('created', '') and 'Waiting for you' not in seen['error']:
            log(f'confirmed in the page: the run is {seen["state"]}')
            return 0
        time.sleep(0.25)
    log(f'FAIL: the run did not start after the confirmation: {seen}')
    return 1


# Runs before the page's own script: the real Notification, wrapped to record each one made.
RECORDER = (
    '(() => { const Real = window.Notification; if (typeof Real !== "function") return; '
    'window.__notes = []; '
    'class Recorded extends Real { '
    'constructor(title, options) { super(title, options); '
    'window.__notes.push({title, body: (options || {}).body || ""}); } '
    'static get permission() { return Real.permission; } '
    'static requestPermission(...a) { return Real.requestPermission(...a); } } '
    'window.Notification = Recorded; })()')

# Set by the page's script (the HTML's own text says "off" before it runs).
NOTIFY_STATE = ('(() => { const e = document.getElementById("notify-toggle"); '
                'return e ? e.dataset.state || null : null; })()')


def wait_value(chrome, what, expression, test, timeout):
    deadline = time.monotonic() + timeout
    seen = None
    while time.monotonic() < deadline:
        seen = chrome.eval(expression)
        if test(seen):
            return seen
        time.sleep(0.25)
    log(f'FAIL: timed out after {timeout} s waiting for {what}; the page shows {seen}')
    return None


def notify_check(chrome, url, start_url, expect):
    parts = urllib.parse.urlsplit(url)
    chrome.send('Browser.grantPermissions',
                {'permissions': ['notifications'],
                 'origin': f'{parts.scheme}://{parts.netloc}'}, session=False)
    chrome.open(url, 1280, 900, init_script=RECORDER)
    if wait_value(chrome, 'the "notify" chip', NOTIFY_STATE, lambda v: v == 'off', 30) is None:
        return 1
    chrome.eval('document.getElementById("notify-toggle").click()')
    if wait_value(chrome, 'notifications on', NOTIFY_STATE, lambda v: v == 'on', 10) is None:
        return 1
    chrome.send('Page.reload')
    time.sleep(1.0)
    if wait_value(chrome, 'notifications still on after a reload', NOTIFY_STATE,
                  lambda v: v == 'on', 30) is None:
        return 1
    log('the "notify" chip is on, and still on after a reload')
    time.sleep(1.0)  # the page has the run's state before it starts
    request = urllib.request.Request(start_url, data=b'{}', method='POST',
                                     headers={'Content-Type': 'application/json'})
    with urllib.request.urlopen(request, timeout=10) as answer:
        log(f'POST {start_url}: {answer.status}')
    notes = wait_value(chrome, f'a notification "...{expect}..."', 'window.__notes || []',
                       lambda v: any(expect in n['title'] for n in v), 120)
    if notes is None:
        return 1
    time.sleep(5.0)  # anything told twice, or late, would be by now
    notes = chrome.eval('window.__notes')
    for n in notes:
        log(f'notification: "{n["title"]}": {n["body"]!r}')
    if len(notes) != 1:
        log(f'FAIL: {len(notes)} notifications (expected one, "...{expect}...")')
        return 1
    chrome.eval('1')
    problems = chrome.problems()
    for p in problems:
        log(f'page problem: {p}')
    return 1 if problems else 0


def main():
    confirm = len(sys.argv) == 6 and sys.argv[1] == '--confirm'
    notify = len(sys.argv) == 8 and sys.argv[1] == '--notify'
    args = sys.argv[2:] if confirm else sys.argv[4:] if notify else sys.argv[1:]
    if len(args) != 4:
        print(__doc__, file=sys.stderr)
        return 2
    binary, url, profile, chrome_log = args
    chrome = Chromium(binary, profile, chrome_log)
    try:
        if confirm:
            return confirm_check(chrome, url)
        if notify:
            return notify_check(chrome, url, sys.argv[2], sys.argv[3])
        chrome.open(url, 1280, 900)
        first = wait_for(chrome, 'the event stream ("live") and a progress number',
                         lambda s: s['live'] == 'live' and (s['done'] or '').isdigit()
                         and int(s['done']) > 0, 30)
        log(f'page open, event stream live: #progress-done={first["done"]} '
            f'#progress-total={first["total"]} #run-state={first["state"]}')
        # Past the page's start-up fetches: from here on (for 15 s) only events change the
        # progress of a streaming page.
        time.sleep(1.0)
        base = chrome.eval(READ)
        t0 = time.monotonic()
        later = wait_for(chrome, '#progress-done to grow without a reload',
                         lambda s: (s['done'] or '').isdigit()
                         and int(s['done']) > int(base['done']), 10)
        log(f'without a reload #progress-done went from {base["done"]} to {later["done"]} '
            f'in {time.monotonic() - t0:.1f} s; events received meanwhile: '
            f'{later["events"] - base["events"]} ({later["events"]} in all; header: '
            f'{later["live"]})')
        if later['live'] != 'live':
            log(f'FAIL: the page fell back to "{later["live"]}" instead of streaming')
            return 1
        if later['events'] <= base['events']:
            log('FAIL: the progress changed, but not through the event stream')
            return 1

        # The new-run form's estimate says, before any run, where nothing will be probed.
        chrome.eval('document.getElementById("new-run-toggle").click()')
        chrome.eval('document.getElementById("new-run-plan").click()')
        deadline = time.monotonic() + 30
        estimate = ''
        while time.monotonic() < deadline:
            estimate = chrome.eval('document.getElementById("new-run-estimate").textContent')
            if 'candidates' in (estimate or ''):
                break
            time.sleep(0.25)
        log(f'the new run\'s estimate: {estimate}')
        if 'candidates' not in (estimate or '') or 'Not probed: z ' not in estimate:
            log('FAIL: the estimate does not say how many probes and where none will be')
            return 1
        chrome.eval('document.getElementById("new-run-toggle").click()')

        chrome.viewport(390, 844, mobile=True)
        time.sleep(1.0)
        layout = chrome.eval(LAYOUT)
        log(f'at 390 px: document {layout["scroll"]} px wide in a {layout["client"]} px '
            f'viewport; runs list ends at y={layout["sidebarBottom"]:.0f}, '
            f'the run starts at y={layout["detailTop"]:.0f}')
        if layout['scroll'] > layout['client']:
            log('FAIL: the page scrolls sideways at a phone\'s width')
            return 1
        if layout['sidebarBottom'] > layout['detailTop'] + 1:
            log('FAIL: the runs list and the run are not in one column at a phone\'s width')
            return 1
        lines = chrome.eval(STAGE_NAME_LINES)
        log(f'a stage name in a 60 px card takes {lines} line(s)')
        if lines != 1:
            log('FAIL: the dashboard breaks a stage name inside the word')
            return 1
        chrome.eval('1')  # collects what is still in the pipe
        problems = chrome.problems()
        for p in problems:
            log(f'page problem: {p}')
        if problems:
            log(f'FAIL: the page reported {len(problems)} problem(s): script errors or '
                'Content-Security-Policy violations')
            return 1
        log('no script error, console warning or CSP violation')
        return 0
    except (ProtocolError, OSError) as e:
        log(f'ERROR: {e}')
        return 2
    finally:
        chrome.close()


if __name__ == '__main__':
    sys.exit(main())
