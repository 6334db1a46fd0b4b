#include "recon/model_bundle.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>

#include <opencv2/imgcodecs.hpp>

#include "base/atomic_file.h"
#include "base/byte_io.h"
#include "base/hash.h"
#include "geometry/bvh.h"

namespace gs360 {
namespace {

using Json = nlohmann::json;
constexpr char kMagic[8] = {'G', 'S', '3', '6', '0', 'B', 'D', 'L'};

class Writer {
 public:
  template <typename T>
  void Pod(const T& v) {
    Raw(&v, sizeof(T));
  }
  void Bytes(std::span<const std::uint8_t> b) { Raw(b.data(), b.size()); }
  void Chunk(const std::string& name, std::span<const std::uint8_t> data) {
    Pod(static_cast<std::uint32_t>(name.size()));
    Raw(name.data(), name.size());
    Pod(static_cast<std::uint64_t>(data.size()));
    Bytes(data);
  }
  std::vector<std::uint8_t>& bytes() { return bytes_; }

 private:
  // resize + memcpy rather than insert: GCC 12 reports a false -Wstringop-overflow for the
  // latter (like bug 105329).
  void Raw(const void* data, std::size_t size) {
    if (size == 0) return;
    const std::size_t at = bytes_.size();
    bytes_.resize(at + size);
    std::memcpy(bytes_.data() + at, data, size);
  }
  std::vector<std::uint8_t> bytes_;
};

class Reader {
 public:
  Reader(std::span<const std::uint8_t> bytes, std::string where, std::string what)
      : bytes_(bytes), where_(std::move(where)), what_(std::move(what)) {}
  template <typename T>
  T Pod() {
    Need(sizeof(T));
    T v;
    std::memcpy(&v, bytes_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return v;
  }
  std::span<const std::uint8_t> Take(std::uint64_t n) {
    Need(n);
    auto s = bytes_.subspan(pos_, n);
    pos_ += n;
    return s;
  }
  bool AtEnd() const { return pos_ == bytes_.size(); }
  std::size_t pos() const { return pos_; }

 private:
  void Need(std::uint64_t n) const {
    if (n > bytes_.size() - pos_) {
      throw ModelBundleError(where_ + ": truncated " + what_ + " (needs " + std::to_string(n) +
                             " more bytes at offset " + std::to_string(pos_) + " of " +
                             std::to_string(bytes_.size()) + ")");
    }
  }
  std::span<const std::uint8_t> bytes_;
  std::size_t pos_ = 0;
  std::string where_, what_;
};

std::vector<std::uint8_t> MeshBytes(const TriangleMesh& mesh) {
  Writer w;
  w.Pod(static_cast<std::uint32_t>(mesh.vertices.size()));
  w.Pod(static_cast<std::uint32_t>(mesh.triangles.size()));
  w.Pod(static_cast<std::uint8_t>(mesh.HasNormals() ? 1 : 0));
  for (const auto& v : mesh.vertices) w.Pod(v.x()), w.Pod(v.y()), w.Pod(v.z());
  for (const auto& t : mesh.triangles) w.Pod(t.x()), w.Pod(t.y()), w.Pod(t.z());
  if (mesh.HasNormals()) {
    for (const auto& n : mesh.normals) w.Pod(n.x()), w.Pod(n.y()), w.Pod(n.z());
  }
  return std::move(w.bytes());
}

TriangleMesh MeshFromBytes(std::span<const std::uint8_t> bytes, const std::string& where,
                           const std::string& name) {
  Reader r(bytes, where, "mesh chunk \"" + name + "\"");
  TriangleMesh mesh;
  const auto nv = r.Pod<std::uint32_t>();
  const auto nt = r.Pod<std::uint32_t>();
  const bool normals = r.Pod<std::uint8_t>() != 0;
  const std::uint64_t expected = 9ull + 24ull * nv + 12ull * nt + (normals ? 24ull * nv : 0ull);
  if (expected != bytes.size()) {
    throw ModelBundleError(where + ": mesh chunk \"" + name + "\" has " +
                           std::to_string(bytes.size()) + " bytes, its header says " +
                           std::to_string(expected));
  }
  mesh.vertices.resize(nv);
  for (auto& v : mesh.vertices) {
    v.x() = r.Pod<double>(), v.y() = r.Pod<double>(), v.z() = r.Pod<double>();
    if (!v.allFinite())
      throw ModelBundleError(where + ": mesh \"" + name + "\" has a non-finite vertex");
  }
  mesh.triangles.resize(nt);
  for (auto& t : mesh.triangles) {
    t.x() = r.Pod<int>(), t.y() = r.Pod<int>(), t.z() = r.Pod<int>();
    if (t.minCoeff() < 0 || t.maxCoeff() >= static_cast<int>(nv)) {
      throw ModelBundleError(where + ": mesh \"" + name + "\" has a vertex index out of range");
    }
  }
  if (normals) {
    mesh.normals.resize(nv);
    for (auto& n : mesh.normals)
      n.x() = r.Pod<double>(), n.y() = r.Pod<double>(), n.z() = r.Pod<double>();
  }
  return mesh;
}

std::span<const std::uint8_t> AsBytes(const std::string& s) {
  return {reinterpret_cast<const std::uint8_t*>(s.data()), s.size()};
}

}  // namespace

Json IntrinsicsToJson(const FisheyeIntrinsics& k) {
  return Json{{"width", k.width}, {"height", k.height}, {"fx", k.fx},
              {"fy", k.fy},       {"cx", k.cx},         {"cy", k.cy},
              {"skew", k.skew},   {"k", k.k},           {"max_theta", k.max_theta}};
}

FisheyeIntrinsics IntrinsicsFromJson(const Json& j) {
  FisheyeIntrinsics k;
  k.width = j.at("width").get<int>();
  k.height = j.at("height").get<int>();
  k.fx = j.at("fx").get<double>();
  k.fy = j.at("fy").get<double>();
  k.cx = j.at("cx").get<double>();
  k.cy = j.at("cy").get<double>();
  k.skew = j.at("skew").get<double>();
  k.k = j.at("k").get<std::array<double, 4>>();
  k.max_theta = j.at("max_theta").get<double>();
  return k;
}

Json PoseToJson(const Rigid3d& p) {
  return Json{{"qw", p.rotation.w()},
              {"qx", p.rotation.x()},
              {"qy", p.rotation.y()},
              {"qz", p.rotation.z()},
              {"t", {p.translation.x(), p.translation.y(), p.translation.z()}}};
}

Rigid3d PoseFromJson(const Json& j) {
  const auto t = j.at("t").get<std::array<double, 3>>();
  return Rigid3d(Eigen::Quaterniond(j.at("qw").get<double>(), j.at("qx").get<double>(),
                                    j.at("qy").get<double>(), j.at("qz").get<double>()),
                 Eigen::Vector3d(t[0], t[1], t[2]));
}

Reconstructor ModelBundle::MakeReconstructor(int threads) const {
  const FisheyeCamera camera(intrinsics);
  const Bvh gel(gel_mesh);
  std::unique_ptr<Bvh> fins;
  if (!fin_mesh.Empty()) fins = std::make_unique<Bvh>(fin_mesh);
  SurfaceMapOptions map_options = surface_map;
  map_options.threads = threads;
  auto map = std::make_shared<const SurfaceMap>(
      SurfaceMap::Build(camera, cam_from_sensor, gel, fins.get(), map_options));
  return Reconstructor(std::move(map), camera, mlp, reference, reconstruction);
}

std::vector<std::uint8_t> SerializeModelBundle(const ModelBundle& b) {
  if (b.reference.type() != CV_8UC3 || b.reference.cols != b.intrinsics.width ||
      b.reference.rows != b.intrinsics.height) {
    throw ModelBundleError("model bundle \"" + b.name +
                           "\": the reference frame must be CV_8UC3 of the camera's size");
  }
  const Json meta{
      {"format", kModelBundleFormat},
      {"name", b.name},
      {"version", b.version},
      {"gs360_version", b.gs360_version},
      {"created_at", b.created_at},
      {"sensor", b.sensor},
      {"intrinsics", IntrinsicsToJson(b.intrinsics)},
      {"cam_from_sensor", PoseToJson(b.cam_from_sensor)},
      {"surface_map",
       {{"max_view_angle_deg", b.surface_map.max_view_angle_deg},
        {"fin_margin_px", b.surface_map.fin_margin_px}}},
      {"reconstruction", ReconstructionOptionsToJson(b.reconstruction)},
      {"metrics", b.metrics},
  };
  std::vector<std::uint8_t> png;
  if (!cv::imencode(".png", b.reference, png)) {
    throw ModelBundleError("model bundle \"" + b.name + "\": could not encode the reference frame");
  }
  Writer w;
  w.Bytes({reinterpret_cast<const std::uint8_t*>(kMagic), sizeof(kMagic)});
  w.Pod(kModelBundleFormat);
  w.Pod(static_cast<std::uint32_t>(5));
  w.Chunk("meta.json", AsBytes(meta.dump(1)));
  w.Chunk("gel_mesh", MeshBytes(b.gel_mesh));
  w.Chunk("fin_mesh", MeshBytes(b.fin_mesh));
  w.Chunk("reference.png", png);
  w.Chunk("mlp", b.mlp.Serialize());
  const std::string sum = HashHex(w.bytes().data(), w.bytes().size());
  w.Bytes(AsBytes(sum));
  return std::move(w.bytes());
}

namespace {

// The bundle's reference frame: a colour PNG of the intrinsics' size, else ModelBundleError.
// Only a PNG goes to OpenCV's decoder, and a broken one is that error, not a cv::Exception.
cv::Mat DecodeReference(std::span<const std::uint8_t> png, const FisheyeIntrinsics& intrinsics,
                        const std::string& where) {
  cv::Mat image;
  if (HasPngSignature(png)) {
    try {
      image = cv::imdecode(
          cv::Mat(1, static_cast<int>(png.size()), CV_8U, const_cast<std::uint8_t*>(png.data())),
          cv::IMREAD_COLOR);
    } catch (const cv::Exception&) {
      image.release();
    }
  }
  if (image.empty() || image.cols != intrinsics.width || image.rows != intrinsics.height) {
    throw ModelBundleError(where + ": the reference frame does not decode to a " +
                           std::to_string(intrinsics.width) + "x" +
                           std::to_string(intrinsics.height) + " colour image");
  }
  return image;
}

}  // namespace

ModelBundle DeserializeModelBundle(std::span<const std::uint8_t> bytes, const std::string& where) {
  if (bytes.size() < sizeof(kMagic) + 8 + 16 ||
      std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) != 0) {
    throw ModelBundleError(where + ": not a gs360 model bundle (bad magic or too short: " +
                           std::to_string(bytes.size()) + " bytes)");
  }
  const auto body = bytes.first(bytes.size() - 16);
  const std::string stored(reinterpret_cast<const char*>(bytes.data() + body.size()), 16);
  const std::string actual = HashHex(body.data(), body.size());
  Reader r(body, where, "model bundle");
  r.Take(sizeof(kMagic));
  const auto format = r.Pod<std::uint32_t>();
  if (format > kModelBundleFormat) {
    throw ModelBundleError(where + ": model bundle format " + std::to_string(format) +
                           " is newer than this gs360 reads (" +
                           std::to_string(kModelBundleFormat) + "); upgrade gs360");
  }
  const bool hex = std::all_of(stored.begin(), stored.end(), [](char c) {
    return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f');
  });
  if (!hex) {
    throw ModelBundleError(where + ": truncated or corrupt (the file does not end in its " +
                           "checksum; " + std::to_string(bytes.size()) + " bytes)");
  }
  if (stored != actual) {
    throw ModelBundleError(where + ": checksum mismatch (stored " + stored + ", computed " +
                           actual + "): the file is corrupt or truncated");
  }
  const auto count = r.Pod<std::uint32_t>();
  std::map<std::string, std::span<const std::uint8_t>> chunks;
  for (std::uint32_t i = 0; i < count; ++i) {
    const auto name_size = r.Pod<std::uint32_t>();
    const auto name_bytes = r.Take(name_size);
    const std::string name(name_bytes.begin(), name_bytes.end());
    const auto size = r.Pod<std::uint64_t>();
    chunks[name] = r.Take(size);
  }
  auto chunk = [&](const std::string& name) {
    auto it = chunks.find(name);
    if (it == chunks.end()) throw ModelBundleError(where + ": missing chunk \"" + name + "\"");
    return it->second;
  };
  ModelBundle b;
  try {
    const auto meta_bytes = chunk("meta.json");
    const Json meta = Json::parse(meta_bytes.begin(), meta_bytes.end());
    b.name = meta.at("name").get<std::string>();
    b.version = meta.at("version").get<std::string>();
    b.gs360_version = meta.at("gs360_version").get<std::string>();
    b.created_at = meta.at("created_at").get<double>();
    b.sensor = meta.at("sensor").get<std::string>();
    b.intrinsics = IntrinsicsFromJson(meta.at("intrinsics"));
    b.intrinsics.Check();
    b.cam_from_sensor = PoseFromJson(meta.at("cam_from_sensor"));
    b.surface_map.max_view_angle_deg =
        meta.at("surface_map").at("max_view_angle_deg").get<double>();
    b.surface_map.fin_margin_px = meta.at("surface_map").at("fin_margin_px").get<double>();
    b.surface_map.Check();
    b.reconstruction =
        ReconstructionOptionsFromJson(meta.at("reconstruction"), where + ": reconstruction");
    b.metrics = meta.at("metrics");
  } catch (const ModelBundleError&) {
    throw;
  } catch (const std::exception& e) {
    throw ModelBundleError(where + ": bad meta.json: " + e.what());
  }
  b.gel_mesh = MeshFromBytes(chunk("gel_mesh"), where, "gel_mesh");
  if (b.gel_mesh.Empty()) throw ModelBundleError(where + ": the gel mesh is empty");
  b.fin_mesh = MeshFromBytes(chunk("fin_mesh"), where, "fin_mesh");
  b.reference = DecodeReference(chunk("reference.png"), b.intrinsics, where);
  try {
    b.mlp = Mlp::Deserialize(chunk("mlp"));
  } catch (const ModelBundleError&) {
    throw;
  } catch (const std::exception& e) {
    throw ModelBundleError(where + ": bad MLP: " + e.what());
  }
  return b;
}

std::vector<std::uint8_t> WriteModelBundle(const std::filesystem::path& path,
                                           const ModelBundle& bundle) {
  const std::vector<std::uint8_t> bytes = SerializeModelBundle(bundle);
  try {
    WriteFileAtomically(
        path, std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
  } catch (const std::runtime_error& e) {
    throw ModelBundleError(e.what());
  }
  return bytes;
}

ModelBundle ReadModelBundle(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ModelBundleError(path.string() + ": cannot open model bundle");
  std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(in)),
                                  std::istreambuf_iterator<char>());
  return DeserializeModelBundle(bytes, path.string());
}

}  // namespace gs360
