#include "capture/frame_source.h"

#include "capture/frame_server.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <mutex>
#include <sstream>
#include <utility>

#include "capture/libcamera_source.h"
#include "capture/replay_source.h"
#include "capture/v4l2_source.h"

namespace gs360 {
namespace {

std::string Num(double v) {
  std::ostringstream out;
  out << v;
  return out.str();
}

bool IsValidScheme(std::string_view scheme) {
  if (scheme.empty() || !std::islower(static_cast<unsigned char>(scheme[0]))) return false;
  return std::all_of(scheme.begin(), scheme.end(), [](char c) {
    const auto u = static_cast<unsigned char>(c);
    return std::islower(u) || std::isdigit(u) || c == '+' || c == '-' || c == '.';
  });
}

struct Registry {
  std::mutex mutex;
  std::map<std::string, FrameSourceFactory> factories;

  Registry() {
    factories["libcamera"] = &OpenLibcameraFrameSource;
    factories["v4l2"] = &OpenV4l2FrameSource;
    factories["replay"] = &OpenReplayFrameSource;
    factories["socket"] = &OpenSocketFrameSource;
  }
};

Registry& GetRegistry() {
  static Registry registry;
  return registry;
}

}  // namespace

#ifndef GS360_HAVE_LIBCAMERA
std::unique_ptr<FrameSource> OpenLibcameraFrameSource(const FrameSourceUri& uri,
                                                      const CameraControls&) {
  throw FrameSourceError(FrameSourceErrc::kNotCompiled, uri.uri,
                         "gs360 was compiled without libcamera support (libcamera was not found "
                         "at configure time or GS360_WITH_LIBCAMERA was OFF)");
}
#endif

#ifndef GS360_HAVE_OPENCV_VIDEOIO
std::unique_ptr<FrameSource> OpenV4l2FrameSource(const FrameSourceUri& uri, const CameraControls&) {
  throw FrameSourceError(FrameSourceErrc::kNotCompiled, uri.uri,
                         "gs360 was compiled without V4L2 support (OpenCV videoio was not found "
                         "at configure time)");
}
#endif

bool HaveLibcameraSupport() {
#ifdef GS360_HAVE_LIBCAMERA
  return true;
#else
  return false;
#endif
}

bool HaveV4l2Support() {
#ifdef GS360_HAVE_OPENCV_VIDEOIO
  return true;
#else
  return false;
#endif
}

void CameraControls::Check() const {
  if (!std::isfinite(exposure_us) || exposure_us <= 0.0 || exposure_us > 10e6) {
    throw std::invalid_argument("CameraControls.exposure_us must be in (0, 1e7] us, got " +
                                Num(exposure_us));
  }
  if (!std::isfinite(analogue_gain) || analogue_gain < 0.0) {
    throw std::invalid_argument("CameraControls.analogue_gain must be finite and >= 0, got " +
                                Num(analogue_gain));
  }
  for (int i = 0; i < 2; ++i) {
    const double g = colour_gains[static_cast<std::size_t>(i)];
    if (!std::isfinite(g) || g <= 0.0) {
      throw std::invalid_argument(std::string("CameraControls.colour_gains[") +
                                  (i == 0 ? "0] (red)" : "1] (blue)") +
                                  " must be finite and > 0, got " + Num(g));
    }
  }
  if (width < 16 || width > 16384) {
    throw std::invalid_argument("CameraControls.width must be in [16, 16384], got " +
                                std::to_string(width));
  }
  if (height < 16 || height > 16384) {
    throw std::invalid_argument("CameraControls.height must be in [16, 16384], got " +
                                std::to_string(height));
  }
}

std::string_view ToString(FrameSourceErrc code) {
  switch (code) {
    case FrameSourceErrc::kBadUri:
      return "bad URI";
    case FrameSourceErrc::kUnknownScheme:
      return "unknown scheme";
    case FrameSourceErrc::kNotCompiled:
      return "backend not compiled";
    case FrameSourceErrc::kNoDevice:
      return "no such device";
    case FrameSourceErrc::kDeviceBusy:
      return "device busy";
    case FrameSourceErrc::kUnsupported:
      return "unsupported settings";
    case FrameSourceErrc::kBadImage:
      return "bad image";
    case FrameSourceErrc::kDisconnected:
      return "disconnected";
    case FrameSourceErrc::kIo:
      return "I/O error";
  }
  return "unknown error";
}

FrameSourceError::FrameSourceError(FrameSourceErrc code, const std::string& uri,
                                   const std::string& detail)
    : std::runtime_error("frame source '" + uri + "': " + detail), code_(code), uri_(uri) {}

FrameSource::~FrameSource() = default;

std::optional<std::string> FrameSourceUri::Option(const std::string& key) const {
  auto it = options.find(key);
  if (it == options.end()) return std::nullopt;
  return it->second;
}

std::optional<double> FrameSourceUri::DoubleOption(const std::string& key) const {
  auto value = Option(key);
  if (!value) return std::nullopt;
  const char* begin = value->c_str();
  char* end = nullptr;
  const double v = std::strtod(begin, &end);
  if (value->empty() || end != begin + value->size() || !std::isfinite(v)) {
    throw FrameSourceError(FrameSourceErrc::kBadUri, uri,
                           "option '" + key + "' must be a number, got '" + *value + "'");
  }
  return v;
}

std::optional<bool> FrameSourceUri::BoolOption(const std::string& key) const {
  auto value = Option(key);
  if (!value) return std::nullopt;
  if (*value == "1" || *value == "true") return true;
  if (*value == "0" || *value == "false") return false;
  throw FrameSourceError(FrameSourceErrc::kBadUri, uri,
                         "option '" + key + "' must be 0, 1, true or false, got '" + *value + "'");
}

void FrameSourceUri::RequireKnownOptions(std::initializer_list<std::string_view> allowed) const {
  for (const auto& [key, value] : options) {
    if (std::find(allowed.begin(), allowed.end(), key) != allowed.end()) continue;
    std::string known;
    for (std::string_view a : allowed) known += (known.empty() ? "" : ", ") + std::string(a);
    throw FrameSourceError(FrameSourceErrc::kBadUri, uri,
                           "unknown option '" + key + "' for scheme '" + scheme +
                               "' (known: " + (known.empty() ? "none" : known) + ")");
  }
}

FrameSourceUri ParseFrameSourceUri(const std::string& uri) {
  FrameSourceUri parsed;
  parsed.uri = uri;
  const std::size_t colon = uri.find(':');
  if (colon == std::string::npos) {
    throw FrameSourceError(FrameSourceErrc::kBadUri, uri,
                           "expected '<scheme>:<target>', e.g. 'v4l2:/dev/video0', "
                           "'libcamera:0' or 'replay:/path/to/folder'");
  }
  parsed.scheme = uri.substr(0, colon);
  if (!IsValidScheme(parsed.scheme)) {
    throw FrameSourceError(FrameSourceErrc::kBadUri, uri,
                           "invalid scheme '" + parsed.scheme +
                               "' (lower-case letters, digits, '+', '-', '.', starting with a "
                               "letter)");
  }
  const std::size_t question = uri.find('?', colon + 1);
  parsed.target = uri.substr(
      colon + 1, question == std::string::npos ? std::string::npos : question - colon - 1);
  if (question != std::string::npos) {
    std::string_view query(uri);
    query.remove_prefix(question + 1);
    while (true) {
      const std::size_t amp = query.find('&');
      const std::string_view item = query.substr(0, amp);
      const std::size_t eq = item.find('=');
      if (eq == std::string_view::npos || eq == 0) {
        throw FrameSourceError(FrameSourceErrc::kBadUri, uri,
                               "option '" + std::string(item) + "' is not of the form key=value");
      }
      std::string key(item.substr(0, eq));
      if (!parsed.options.emplace(key, std::string(item.substr(eq + 1))).second) {
        throw FrameSourceError(FrameSourceErrc::kBadUri, uri,
                               "option '" + key + "' given more than once");
      }
      if (amp == std::string_view::npos) break;
      query.remove_prefix(amp + 1);
    }
  }
  return parsed;
}

bool RegisterFrameSourceFactory(const std::string& scheme, FrameSourceFactory factory) {
  if (!IsValidScheme(scheme)) {
    throw std::invalid_argument("RegisterFrameSourceFactory: invalid scheme '" + scheme +
                                "' (lower-case letters, digits, '+', '-', '.', starting with a "
                                "letter)");
  }
  if (!factory) {
    throw std::invalid_argument("RegisterFrameSourceFactory: empty factory for scheme '" + scheme +
                                "'");
  }
  Registry& registry = GetRegistry();
  std::lock_guard lock(registry.mutex);
  auto [it, inserted] = registry.factories.insert_or_assign(scheme, std::move(factory));
  (void)it;
  return !inserted;
}

bool UnregisterFrameSourceFactory(const std::string& scheme) {
  Registry& registry = GetRegistry();
  std::lock_guard lock(registry.mutex);
  return registry.factories.erase(scheme) > 0;
}

std::vector<std::string> FrameSourceSchemes() {
  Registry& registry = GetRegistry();
  std::lock_guard lock(registry.mutex);
  std::vector<std::string> schemes;
  for (const auto& [scheme, factory] : registry.factories) schemes.push_back(scheme);
  return schemes;  // std::map: already sorted
}

std::unique_ptr<FrameSource> OpenFrameSource(const std::string& uri,
                                             const CameraControls& controls) {
  controls.Check();
  const FrameSourceUri parsed = ParseFrameSourceUri(uri);
  FrameSourceFactory factory;
  std::string known;
  {
    Registry& registry = GetRegistry();
    std::lock_guard lock(registry.mutex);
    auto it = registry.factories.find(parsed.scheme);
    if (it != registry.factories.end()) {
      factory = it->second;  // copied: the factory runs without the lock held
    } else {
      for (const auto& [scheme, f] : registry.factories) {
        known += (known.empty() ? "" : ", ") + scheme;
      }
    }
  }
  if (!factory) {
    throw FrameSourceError(FrameSourceErrc::kUnknownScheme, uri,
                           "unknown frame source scheme '" + parsed.scheme +
                               "' (known: " + (known.empty() ? "none" : known) + ")");
  }
  std::unique_ptr<FrameSource> source = factory(parsed, controls);
  if (!source) {
    throw FrameSourceError(FrameSourceErrc::kIo, uri,
                           "the factory for scheme '" + parsed.scheme + "' returned no source");
  }
  return source;
}

}  // namespace gs360
