#pragma once
// V4L2 / UVC cameras through OpenCV's V4L2 backend (cv::VideoCapture with cv::CAP_V4L2).
//
// URI: "v4l2:/dev/videoN" or "v4l2:N", options:
//   fourcc=MJPG|YUYV|...   pixel format asked of the camera (UVC cameras often need MJPG for
//                          large sizes; MJPG costs a decode per frame)
//   fps=<rate>             frame rate asked of the camera
//   buffers=<n>            driver buffer count (1..16; fewer buffers = fresher frames)
//   wb_temperature=<K>     fixed white-balance temperature (with lock)
//
// Settings (raw V4L2 control values, as OpenCV 4.x passes them through): with controls.lock,
// V4L2_CID_EXPOSURE_AUTO = 1 (manual), V4L2_CID_EXPOSURE_ABSOLUTE = exposure_us / 100 (the control
// counts 100 us units), V4L2_CID_GAIN = analogue_gain (device units),
// V4L2_CID_AUTO_WHITE_BALANCE = 0. A camera that refuses manual exposure or the frame size makes
// opening fail (kUnsupported); a refused gain or white-balance setting is logged as a warning.
// colour_gains are not applied (OpenCV maps no per-channel gain control for V4L2).
//
// Timestamps: the V4L2 buffer timestamp (CAP_PROP_POS_MSEC; CLOCK_MONOTONIC, the clock behind
// steady_clock, stamped by uvcvideo when the frame's first bytes arrive, i.e. after the exposure)
// when it lies within the last 10 s of the host clock; otherwise the host steady_clock time at
// which the frame was dequeued. exposure = controls.exposure_us.
//
// Next() waits with cv::VideoCapture::waitAny, so the timeout is honoured.

#include <memory>

#include "capture/frame_source.h"

namespace gs360 {

// Factory for the "v4l2" scheme. Throws FrameSourceError naming the URI and the device:
// kNoDevice if the device node does not exist or is not a character device, kIo if it is not a
// V4L2 capture device, kUnsupported for refused settings, kNotCompiled without OpenCV videoio.
std::unique_ptr<FrameSource> OpenV4l2FrameSource(const FrameSourceUri& uri,
                                                 const CameraControls& controls);

}  // namespace gs360
