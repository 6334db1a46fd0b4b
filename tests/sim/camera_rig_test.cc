// The simulated rig's description (nominal vs true camera, mount) and the cross-LED lighting.
#include <catch2/catch.hpp>

#include <cmath>
#include <numbers>

#include "camera_test_util.h"
#include "geometry/rigid3.h"
#include "geometry/shapes.h"
#include "sim/ground_truth.h"
#include "sim/lighting.h"
#include "sim/rig_model.h"

using namespace gs360;
using namespace gs360::camera_test;

TEST_CASE("rig: the true camera differs from the nominal one by the stated amounts",
          "[sim][camera]") {
  const SimRigOptions options;
  const SimRig rig(options);
  const Rigid3d nominal = rig.nominal_cam_from_sensor();
  const Rigid3d truth = SimGroundTruth::TrueCamFromSensor(rig);
  // Camera centres (sensor frame) 0.3 mm apart; orientations 1 deg apart.
  const Eigen::Vector3d c_nominal = nominal.Inverse().translation;
  const Eigen::Vector3d c_true = truth.Inverse().translation;
  CHECK(c_nominal.isApprox(Eigen::Vector3d(0.0, 0.0, options.rig.camera_z)));
  CHECK((c_true - c_nominal).norm() == Approx(options.perturbation.translation_mm).margin(1e-12));
  CHECK(RotationDifferenceRad(nominal, truth) ==
        Approx(Deg(options.perturbation.rotation_deg)).margin(1e-9));
  const FisheyeIntrinsics& n = rig.nominal_intrinsics();
  const FisheyeIntrinsics& t = SimGroundTruth::TrueIntrinsics(rig);
  CHECK(std::abs(t.fx / n.fx - 1.0) == Approx(options.perturbation.focal_relative).margin(1e-12));
  CHECK(std::abs((t.fy / t.fx) / (n.fy / n.fx) - 1.0) ==
        Approx(options.perturbation.aspect_relative).margin(1e-12));
  CHECK(std::hypot(t.cx - n.cx, t.cy - n.cy) == Approx(options.perturbation.principal_point_px));
  CHECK(std::abs(t.k[0]) == Approx(options.perturbation.k1));
  CHECK(std::abs(t.k[1]) == Approx(options.perturbation.k2));

  // Seeded: the same seed gives the same true camera, another seed another one.
  const SimRig same(options);
  CHECK(TranslationDifferenceMm(SimGroundTruth::TrueCamFromSensor(same), truth) == 0.0);
  SimRigOptions other = options;
  other.seed = 99;
  const SimRig different(other);
  CHECK(TranslationDifferenceMm(SimGroundTruth::TrueCamFromSensor(different), truth) > 1e-3);

  // No perturbation: the truth is the nominal camera.
  SimRigOptions exact = options;
  exact.perturbation = TruePerturbationOptions::None();
  const SimRig exact_rig(exact);
  CHECK(TranslationDifferenceMm(SimGroundTruth::TrueCamFromSensor(exact_rig), nominal) < 1e-12);
  CHECK(SimGroundTruth::TrueIntrinsics(exact_rig).fx == n.fx);
}

TEST_CASE("rig: machine and sensor positions of the ball", "[sim][camera]") {
  SimRigOptions options;
  options.rig.base_in_machine = Eigen::Vector3d(-90.0, -110.0, -140.0);
  options.rig.tool_offset = Eigen::Vector3d(0.5, -0.2, -38.0);
  const SimRig rig(options);
  const Eigen::Vector3d ball(3.0, -4.0, 12.0);
  const Eigen::Vector3d machine = rig.MachinePositionForBall(ball);
  CHECK((rig.BallCenterSensor(machine) - ball).norm() < 1e-12);
  // Ball centre = machine position + tool offset, in the machine frame.
  CHECK(((machine + options.rig.tool_offset) - options.rig.machine_from_sensor() * ball).norm() <
        1e-12);
  // The default mount keeps the sensor inside the negative travel of a CNC homed at 0.
  const SimRigOptions defaults;
  const SimRig default_rig(defaults);
  const Eigen::Vector3d tip_press =
      default_rig.MachinePositionForBall(Eigen::Vector3d(0, 0, 30.0 + 2.0 - 1.0));
  CHECK((tip_press.array() < 0.0).all());
  CHECK((tip_press.array() > -200.0).all());
}

TEST_CASE("rig: options are checked, naming the field", "[sim][camera]") {
  // (Named copies of a default, not SimRigOptions{} temporaries: GCC 12 reports a false
  // -Wmaybe-uninitialized on the nested spline control-point vector of a temporary.)
  const SimRigOptions defaults;
  SimRigOptions bad = defaults;
  bad.rig.camera_z = 2.0;  // above the fins' bottom edge
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("camera_z"));
  bad = defaults;
  bad.rig.ball_radius = 0.0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("ball_radius"));
  bad = defaults;
  bad.perturbation.rotation_deg = -1.0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("rotation_deg"));
  bad = defaults;
  bad.perturbation.k1 = 0.5;  // folds the lens inside 80 deg
  CHECK_THROWS_AS(SimRig(bad), std::invalid_argument);
  bad = defaults;
  bad.rig.mesh_path = "/nonexistent/finger.stl";
  CHECK_THROWS_AS(SimRig(bad), MeshError);
}

TEST_CASE("lighting: LED layout, fin shadows and per-channel shading", "[sim][camera]") {
  const SensorShapeOptions shape;
  const auto profile = MakeProfile(shape);
  const FinOptions fins = RigConfig::DefaultFins();
  const LightingOptions options;
  const Lighting lighting(options, *profile, fins);
  int per_channel[3] = {0, 0, 0};
  for (const Led& led : lighting.leds()) {
    ++per_channel[led.channel];
    if (led.channel == 0) CHECK(std::abs(led.position.y()) == Approx(fins.thickness / 2));
    if (led.channel == 1) CHECK(std::abs(led.position.x()) == Approx(fins.thickness / 2));
    if (led.channel == 2) CHECK(led.axis.isApprox(Eigen::Vector3d::UnitZ()));
  }
  const int fin_leds = 8 * static_cast<int>(options.fin_led_heights.size());
  CHECK(per_channel[0] == fin_leds / 2);
  CHECK(per_channel[1] == fin_leds / 2);
  CHECK(per_channel[2] == options.blue_ring_count);

  // The yz fin (x = 0) blocks a path that crosses it inside its outline, not one above the tip
  // or one that stays on one side.
  CHECK(lighting.FinBlocks(Eigen::Vector3d(-3, 2, 10), Eigen::Vector3d(3, 2, 10)));
  CHECK_FALSE(lighting.FinBlocks(Eigen::Vector3d(1, 2, 10), Eigen::Vector3d(3, 5, 12)));
  CHECK_FALSE(lighting.FinBlocks(Eigen::Vector3d(-3, 2, 35), Eigen::Vector3d(3, 2, 35)));
  CHECK_FALSE(
      lighting.FinBlocks(Eigen::Vector3d(-3, 2, 0.5), Eigen::Vector3d(3, 2, 0.5)));  // below

  // Wall point between the fins, facing inward: lit in every channel; a point the red LEDs'
  // lobes cannot reach (on the fin plane's edge, normal along the board) gets no red.
  const Eigen::Vector3d p = profile->SurfacePoint(0.3, Deg(45.0));
  const Eigen::Vector3d n = profile->SurfaceNormal(0.3, Deg(45.0));
  const Eigen::Vector3d to_camera = (Eigen::Vector3d(0, 0, -1.5) - p).normalized();
  const Eigen::Array3d lit = lighting.Shade(p, n, to_camera);
  CHECK((lit > 0.0).all());
  // Facing outward (the normal flipped) the coating is lit from behind: nothing.
  CHECK((lighting.Shade(p, -n, to_camera) == 0.0).all());
  // Inverse-square fall-off: the tip, far from the fin LEDs, is lit mostly by blue.
  const Eigen::Vector3d tip = profile->SurfacePoint(1.0, 0.0);
  const Eigen::Array3d at_tip =
      lighting.Shade(tip, Eigen::Vector3d::UnitZ(), -Eigen::Vector3d::UnitZ());
  CHECK(at_tip[2] > 5.0 * std::max(at_tip[0], at_tip[1]));

  // Without fins the LEDs stand where the boards would, and nothing casts a shadow.
  FinOptions none = fins;
  none.enabled = false;
  const Lighting bare(options, *profile, none);
  REQUIRE(bare.leds().size() == lighting.leds().size());
  for (std::size_t i = 0; i < bare.leds().size(); ++i) {
    CHECK(bare.leds()[i].position.isApprox(lighting.leds()[i].position));
  }
  CHECK_FALSE(bare.FinBlocks(Eigen::Vector3d(-3, 2, 10), Eigen::Vector3d(3, 2, 10)));

  LightingOptions bad;
  bad.fin_led_heights = {1.5};
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("fin_led_heights"));
  bad = LightingOptions{};
  bad.shininess = 0;
  CHECK_THROWS_WITH(bad.Check(), Catch::Contains("shininess"));
}
