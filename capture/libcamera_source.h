#pragma once
// libcamera cameras (written against libcamera 0.0.3, the version Debian 12 ships).
//
// URI: "libcamera:<index>" (position in libcamera's camera list, e.g. "libcamera:0") or
// "libcamera:<camera id>" (as libcamera names it, e.g. a device-tree path), options:
//   buffers=<n>   frame buffers to allocate (2..16; default: the pipeline's suggestion)
//
// One viewfinder stream at exactly controls.width x controls.height, in the first pixel format the
// pipeline offers among RGB888, BGR888, XRGB8888, XBGR8888, YUYV, NV12, YUV420, MJPEG (converted
// to BGR per frame). Controls, applied to every request: with lock, AeEnable = false,
// AwbEnable = false, ExposureTime, AnalogueGain, ColourGains; controls the camera does not
// advertise are skipped with a warning. Without lock only the enables are set (true).
//
// Timestamps: libcamera's SensorTimestamp metadata (start of the first row's exposure, in ns).
// libcamera documents it as CLOCK_BOOTTIME; the pipeline handlers of 0.0.3 actually copy the V4L2
// buffer timestamp, which Linux drivers take from CLOCK_MONOTONIC. steady_clock is CLOCK_MONOTONIC
// (libstdc++ / libc++ on Linux), and the two clocks differ only by the time spent suspended. So:
// if the value is within 10 s of CLOCK_MONOTONIC it is used as is; else, if it is within 10 s of
// CLOCK_BOOTTIME, it is moved by (MONOTONIC - BOOTTIME) sampled at reception; else the host
// steady_clock time at completion stands in. Frame::timestamp = that + ExposureTime metadata (the
// end of the first row's exposure), Frame::exposure = ExposureTime.
//
// Buffering: the camera streams continuously. At most two completed frames are held for the
// consumer; when a third completes, the oldest is recycled (dropped, visible as a sequence gap),
// so Next() after a pause returns recent frames and the camera never starves.
//
// libcamera allows one CameraManager per process: all libcamera sources share one, started on
// first use and stopped when the last source is destroyed.

#include <memory>

#include "capture/frame_source.h"

namespace gs360 {

// Factory for the "libcamera" scheme. Throws FrameSourceError naming the URI: kNoDevice when
// libcamera finds no camera / no camera with that index or id (the message lists the ids found),
// kDeviceBusy if the camera is in use, kUnsupported if the size or no convertible pixel format is
// available, kNotCompiled when gs360 was built without libcamera (see HaveLibcameraSupport()).
std::unique_ptr<FrameSource> OpenLibcameraFrameSource(const FrameSourceUri& uri,
                                                      const CameraControls& controls);

}  // namespace gs360
