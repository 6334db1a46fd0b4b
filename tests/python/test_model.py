"""The gs360 Python module against a model calibrated on the virtual rig.

  test_model.py DATA_DIR   (written by make_model; PYTHONPATH must hold the built module)
"""
import os
import sys
import threading
import warnings

import numpy as np

import gs360

failures = []


def check(ok, what):
    print(('ok   ' if ok else 'FAIL ') + what, flush=True)
    if not ok:
        failures.append(what)


def main():
    data = sys.argv[1]
    model = gs360.Model.load(os.path.join(data, 'model.gs360model'))
    width, height = model.size
    check((width, height) == (640, 480), f'size {model.size}')
    frame = np.fromfile(os.path.join(data, 'press.bgr'), dtype=np.uint8).reshape(height, width, 3)
    empty = np.fromfile(os.path.join(data, 'empty.bgr'), dtype=np.uint8).reshape(height, width, 3)

    depth, points, contacts = model.reconstruct(frame)
    check(depth.shape == (480, 640) and depth.dtype == np.float32, f'depth {depth.shape} {depth.dtype}')
    check(0.5 < depth.max() < 1.5, f'a 1 mm press peaks at {depth.max():.3f} mm')
    check(points.ndim == 2 and points.shape[1] == 3 and points.shape[0] > 100,
          f'points {points.shape}')
    radius = np.hypot(points[:, 0], points[:, 1])
    check(abs(float(np.median(radius)) - 10.0) < 1.5,
          f'points on the 10 mm cylinder (median radius {np.median(radius):.2f} mm)')
    check(len(contacts) == 1 and abs(contacts[0]['peak_indentation_mm'] - float(depth.max())) < 1e-3,
          f'one contact: {contacts}')
    check(depth.flags['OWNDATA'] is False and depth.base is not None,
          'depth handed over without a copy (owned by a capsule)')

    d0, p0, c0 = model.reconstruct(empty)
    check(len(c0) == 0 and p0.shape == (0, 3) and float(d0.max()) == 0.0, 'no contact, no depth')

    # A black frame (the LEDs off, a cable loose) is no contact at all, and says why.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        db, pb, cb = model.reconstruct(np.zeros_like(frame))
    check(len(cb) == 0 and pb.shape == (0, 3) and float(db.max()) == 0.0, 'a black frame: no depth')
    check(len(caught) == 1 and issubclass(caught[0].category, RuntimeWarning) and
          'frame not reconstructed' in str(caught[0].message),
          f'a black frame warns: {[str(w.message) for w in caught]}')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        model.reconstruct(frame)
    check(len(caught) == 0, 'a good frame does not warn')

    # An explicit reference; and the frame read in place from a non-copied view.
    d1, _, _ = model.reconstruct(frame, reference=model.reference)
    check(np.array_equal(d1, depth), 'reference=model.reference gives the same depth')

    # Frames in flight on two threads at once give the same result as one at a time.
    results = [None, None]

    def run(i):
        results[i] = model.reconstruct(frame)[0]

    threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    check(all(np.array_equal(r, depth) for r in results), 'two threads agree')

    try:
        model.reconstruct(frame[:, :, :2].copy())
        check(False, 'a 2-channel frame is refused')
    except ValueError as e:
        check('480 x 640 x 3' in str(e), f'a 2-channel frame is refused: {e}')

    truncated = os.path.join(data, 'truncated.gs360model')
    with open(os.path.join(data, 'model.gs360model'), 'rb') as f:
        blob = f.read()
    with open(truncated, 'wb') as f:
        f.write(blob[: len(blob) // 2])
    try:
        gs360.Model.load(truncated)
        check(False, 'a truncated model is refused')
    except RuntimeError as e:
        check(truncated in str(e), f'a truncated model is refused naming it: {e}')

    print(f'{len(failures)} failure(s)')
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
