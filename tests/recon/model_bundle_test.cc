#include <catch2/catch.hpp>

#include <filesystem>
#include <fstream>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "geometry/shapes.h"
#include "recon/model_bundle.h"

using namespace gs360;

namespace {
ModelBundle SmallBundle() {
  ModelBundle b;
  b.name = "test-model";
  b.version = "7";
  b.gs360_version = "0.1.0";
  b.created_at = 1.7e9;
  b.sensor = "cylinder";
  b.intrinsics = FisheyeIntrinsics::Default160(160, 120);
  b.cam_from_sensor =
      Rigid3d::FromAxisAngle(Eigen::Vector3d(1, 2, 3), 0.01, Eigen::Vector3d(0.1, -0.2, 1.5));
  SensorShapeOptions shape;
  shape.tessellation.segments = 32;
  b.gel_mesh = MakeSensorMesh(shape);
  b.fin_mesh = MakeFins(FinOptions{}, *MakeProfile(shape));
  b.reference = cv::Mat(120, 160, CV_8UC3, cv::Scalar(70, 110, 150));
  b.mlp = Mlp({5, 8, 2}, Activation::kTanh, 3);
  b.reconstruction.integration.method = IntegrationMethod::kPoisson;
  b.reconstruction.difference.context_sigmas_px.clear();  // the 5-input MLP above
  b.metrics = {{"mean_mm", 0.021}};
  return b;
}
}  // namespace

TEST_CASE("model bundle: round trip keeps everything reconstruction needs", "[recon][bundle]") {
  const ModelBundle b = SmallBundle();
  const auto bytes = SerializeModelBundle(b);
  const ModelBundle c = DeserializeModelBundle(bytes, "memory");
  CHECK(c.name == b.name);
  CHECK(c.version == b.version);
  CHECK(c.intrinsics.fx == b.intrinsics.fx);
  CHECK(c.intrinsics.width == 160);
  CHECK(RotationDifferenceRad(c.cam_from_sensor, b.cam_from_sensor) < 1e-15);
  CHECK(TranslationDifferenceMm(c.cam_from_sensor, b.cam_from_sensor) < 1e-15);
  CHECK(c.gel_mesh.NumTriangles() == b.gel_mesh.NumTriangles());
  CHECK(c.gel_mesh.vertices[5] == b.gel_mesh.vertices[5]);
  CHECK(c.fin_mesh.NumTriangles() == b.fin_mesh.NumTriangles());
  CHECK(cv::countNonZero(c.reference.reshape(1) != b.reference.reshape(1)) == 0);
  CHECK(c.reconstruction.integration.method == IntegrationMethod::kPoisson);
  CHECK(c.metrics.at("mean_mm").get<double>() == 0.021);
  const Eigen::MatrixXf x = Eigen::MatrixXf::Random(5, 7);
  CHECK((c.mlp.Forward(x) - b.mlp.Forward(x)).cwiseAbs().maxCoeff() == 0.0f);
  // Serialising again gives the same bytes (deterministic).
  CHECK(SerializeModelBundle(c) == bytes);
}

TEST_CASE("model bundle: truncated, corrupt and newer files are refused by name",
          "[recon][bundle]") {
  const auto bytes = SerializeModelBundle(SmallBundle());
  for (std::size_t cut :
       {std::size_t{0}, std::size_t{7}, std::size_t{20}, bytes.size() / 2, bytes.size() - 1}) {
    std::vector<std::uint8_t> t(bytes.begin(), bytes.begin() + static_cast<std::ptrdiff_t>(cut));
    CHECK_THROWS_AS(DeserializeModelBundle(t, "cut.gs360model"), ModelBundleError);
  }
  std::vector<std::uint8_t> flipped = bytes;
  flipped[bytes.size() / 3] ^= 0x10;
  CHECK_THROWS_WITH(DeserializeModelBundle(flipped, "flip.gs360model"),
                    Catch::Contains("flip.gs360model") && Catch::Contains("checksum"));
  std::vector<std::uint8_t> newer = bytes;
  newer[8] = 99;  // format version
  CHECK_THROWS_WITH(DeserializeModelBundle(newer, "new.gs360model"), Catch::Contains("newer"));
  const std::vector<std::uint8_t> junk(300, 'x');
  CHECK_THROWS_WITH(DeserializeModelBundle(junk, "junk.bin"), Catch::Contains("not a gs360"));
}

TEST_CASE("model bundle: files are written atomically and read back, and build a reconstructor",
          "[recon][bundle]") {
  const auto dir = std::filesystem::temp_directory_path() / "gs360_bundle_test";
  std::filesystem::create_directories(dir);
  const auto path = dir / "m.gs360model";
  const ModelBundle b = SmallBundle();
  WriteModelBundle(path, b);
  CHECK_FALSE(std::filesystem::exists(dir / "m.gs360model.tmp"));
  const ModelBundle c = ReadModelBundle(path);
  CHECK(c.name == "test-model");
  const Reconstructor r = c.MakeReconstructor(1);
  CHECK(r.map().stats().visible > 1000);
  // The reference itself shows no contact.
  CHECK(r.Reconstruct(c.reference).regions.empty());
  CHECK_THROWS_WITH(ReadModelBundle(dir / "missing.gs360model"), Catch::Contains("missing"));
  std::filesystem::remove_all(dir);
}

TEST_CASE("model bundle: context scales travel with the model, and must match its MLP",
          "[recon][bundle]") {
  ModelBundle b = SmallBundle();
  b.reconstruction.difference.context_sigmas_px = {1.5, 4.0};
  b.mlp = Mlp({FeatureCount(b.reconstruction.difference), 8, 2}, Activation::kTanh, 3);
  const ModelBundle c = DeserializeModelBundle(SerializeModelBundle(b), "memory");
  CHECK(c.reconstruction.difference.context_sigmas_px == std::vector<double>{1.5, 4.0});
  const Reconstructor r = c.MakeReconstructor(1);
  // A frame with a bright spot goes through the 17-input MLP.
  cv::Mat frame = c.reference.clone();
  cv::circle(frame, cv::Point(80, 40), 6, cv::Scalar(120, 160, 200), -1);
  const FrameReconstruction rec = r.Reconstruct(frame);
  CHECK_FALSE(rec.regions.empty());
  // A model written before the context features has no context_sigmas_px: it means none, so
  // its 5-input MLP still loads and runs (the default today would be three scales).
  nlohmann::json old = ReconstructionOptionsToJson(SmallBundle().reconstruction);
  old["difference"].erase("context_sigmas_px");
  CHECK(ReconstructionOptionsFromJson(old, "old bundle").difference.context_sigmas_px.empty());
  CHECK(ReconstructionOptionsFromJson(ReconstructionOptionsToJson(b.reconstruction), "new")
            .difference.context_sigmas_px == std::vector<double>{1.5, 4.0});
  // One written before the oblique pass count existed ran its height_field_iterations
  // everywhere, and still does.
  nlohmann::json one_count = ReconstructionOptionsToJson(SmallBundle().reconstruction);
  one_count["integration"]["height_field_iterations"] = 6;
  one_count["integration"].erase("height_field_oblique_iterations");
  one_count["integration"].erase("height_field_oblique_view_angle_deg");
  const HeightFieldOptions hf =
      ReconstructionOptionsFromJson(one_count, "old bundle").integration.height_field;
  CHECK(hf.Passes(10.0) == 6);
  CHECK(hf.Passes(70.0) == 6);
  nlohmann::json split = ReconstructionOptionsToJson(SmallBundle().reconstruction);
  split["integration"]["height_field_oblique_iterations"] = 3;
  split["integration"]["height_field_oblique_view_angle_deg"] = 45.0;
  const HeightFieldOptions hf2 =
      ReconstructionOptionsFromJson(split, "new bundle").integration.height_field;
  CHECK(hf2.Passes(44.0) == HeightFieldOptions{}.iterations);
  CHECK(hf2.Passes(45.0) == 3);
  split["integration"]["height_field_oblique_iterations"] = 0;
  CHECK_THROWS_WITH(ReconstructionOptionsFromJson(split, "bad bundle"),
                    Catch::Contains("bad bundle") && Catch::Contains("oblique_iterations"));
  // The height field's window travels with the model; a bundle from before it gets the default.
  split["integration"]["height_field_oblique_iterations"] = 3;
  split["integration"]["height_field_window_grow_fraction"] = 0.25;
  CHECK(ReconstructionOptionsFromJson(split, "new bundle")
            .integration.height_field.window_grow_fraction == 0.25);
  split["integration"].erase("height_field_window_grow_fraction");
  CHECK(ReconstructionOptionsFromJson(split, "old bundle")
            .integration.height_field.window_grow_fraction ==
        HeightFieldOptions{}.window_grow_fraction);
  split["integration"]["height_field_window_grow_fraction"] = -1.0;
  CHECK_THROWS_WITH(ReconstructionOptionsFromJson(split, "bad bundle"),
                    Catch::Contains("bad bundle") && Catch::Contains("window_grow_fraction"));
  // The options say 11 inputs, the MLP takes 5: refused, naming both.
  ModelBundle wrong = SmallBundle();
  wrong.reconstruction.difference.context_sigmas_px = {2.0};
  CHECK_THROWS_WITH(wrong.MakeReconstructor(1),
                    Catch::Contains("maps 5 -> 2") && Catch::Contains("expected 11"));
}
