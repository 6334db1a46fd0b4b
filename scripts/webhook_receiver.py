#!/usr/bin/env python3
"""A webhook receiver to try gs360d's [[notify]] tables with, on this machine:

  scripts/webhook_receiver.py [--port 8765] [--out notifications.jsonl] [--status 200]
                              [--delay SECONDS]

Listens on 127.0.0.1, answers every POST with --status after --delay seconds (a slow or hanging
receiver), and appends one JSON line per request to
--out (and a short line to stdout): the time it arrived, the path, the content type, the body
(parsed when it is JSON; its size otherwise, e.g. an ntfy attachment) and, for a JSON body with
"frame_png_base64", the frame's size in bytes. Point a [[notify]] table at it:

  [[notify]]
  url = "http://127.0.0.1:8765/hook"

Ctrl-C stops it. Python standard library only.
"""
import argparse
import base64
import http.server
import json
import sys
import time


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--port', type=int, default=8765)
    parser.add_argument('--out', default='notifications.jsonl')
    parser.add_argument('--status', type=int, default=200, help='HTTP status to answer with')
    parser.add_argument('--delay', type=float, default=0.0, help='seconds before answering')
    args = parser.parse_args()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_POST(self):
            length = int(self.headers.get('Content-Length') or 0)
            if length > 64 * 1024 * 1024:
                self.send_error(413)
                return
            body = self.rfile.read(length)
            record = {'time': time.time(), 'path': self.path,
                      'content_type': self.headers.get('Content-Type', ''),
                      'title': self.headers.get('Title')}
            try:
                record['body'] = json.loads(body)
                frame = record['body'].pop('frame_png_base64', None)
                if frame is not None:
                    record['frame_png_bytes'] = len(base64.b64decode(frame))
            except ValueError:
                record['body_bytes'] = len(body)
            with open(args.out, 'a', encoding='utf-8') as out:
                out.write(json.dumps(record) + '\n')
            b = record.get('body') if isinstance(record.get('body'), dict) else {}
            print(f'{time.strftime("%H:%M:%S")} {self.path} {b.get("event", "?")}: '
                  f'{b.get("title", record["title"])}', flush=True)
            if args.delay > 0:
                time.sleep(args.delay)
            self.send_response(args.status)
            self.send_header('Content-Length', '2')
            self.end_headers()
            self.wfile.write(b'ok')

        def log_message(self, *_):
            pass

    server = http.server.ThreadingHTTPServer(('127.0.0.1', args.port), Handler)
    print(f'webhook receiver on http://127.0.0.1:{server.server_address[1]}/, writing {args.out}',
          flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == '__main__':
    sys.exit(main())
