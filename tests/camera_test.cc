// Camera file parsing and the lens model.
#include "irmosaic/camera.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "irmosaic/error.h"

namespace irmosaic {
namespace {

std::string ErrorOf(const std::string& json_text) {
  const auto path = std::filesystem::temp_directory_path() /
                    ("irmosaic_camera_test_" + std::to_string(::getpid()) + ".json");
  std::ofstream(path) << json_text;
  try {
    CameraModel::LoadJson(path.string());
  } catch (const InputError& e) {
    std::filesystem::remove(path);
    return e.what();
  }
  std::filesystem::remove(path);
  ADD_FAILURE() << "no error for " << json_text;
  return "";
}

TEST(CameraTest, BadFieldsAreNamed) {
  const std::vector<std::pair<std::string, std::string>> cases = {
      {R"({"width": 640, "height": 512, "fy": 2400})", "'fx'"},
      {R"({"width": 640, "height": 512, "fx": 0, "fy": 2400})", "'fx'"},
      {R"({"width": 640, "height": 512, "fx": -5, "fy": 2400})", "'fx'"},
      {R"({"width": 640, "height": 512, "fx": 2400, "fy": 2400, "cx": 700})", "'cx'"},
      {R"({"width": 640, "height": 512, "fx": 2400, "fy": 2400, "cy": -30})", "'cy'"},
      {R"({"width": 640, "height": 512, "fx": "2400", "fy": 2400})", "'fx'"},
      {R"({"width": 640, "fx": 2400, "fy": 2400})", "'height'"},
      {R"({"width": 640.5, "height": 512, "fx": 2400, "fy": 2400})", "'width'"},
      {R"({"width": 640, "height": 512, "fx": 2400, "fy": 2400, "focal": 3})", "'focal'"},
      {R"({"width": 640, "height": 512, "fx": 2400, "fy": 2400, "distortion": [1, 2]})",
       "'distortion'"},
      {R"({"width": 640, "height": 512, "fx": 2400, "fy": 2400, "lever_arm_m": [0, 0]})",
       "'lever_arm_m'"},
      {R"({"width": 640, "height": )", "not valid JSON"},
      {R"([1, 2, 3])", "not a JSON object"},
      // A number beyond double threw nlohmann's out_of_range past LoadJson (found by fuzzing).
      {R"({"width": 555e555, "height": 512, "fx": 2400, "fy": 2400})", "not valid JSON"},
  };
  for (const auto& [text, expected] : cases) {
    const std::string message = ErrorOf(text);
    EXPECT_NE(message.find(expected), std::string::npos) << text << " -> " << message;
  }
}

TEST(CameraTest, SaveLoadRoundTripAndDistortionInverse) {
  CameraModel camera = DefaultInfraredCamera();
  camera.distortion = {-0.12, 0.03, 0.001, -0.0005, 0.0};
  camera.boresight_deg = {0.1, -0.2, 0.3};
  camera.lever_arm_m = {0.5, 0.0, 0.2};
  const auto path = std::filesystem::temp_directory_path() / "irmosaic_camera_roundtrip.json";
  camera.SaveJson(path.string());
  const CameraModel back = CameraModel::LoadJson(path.string());
  std::filesystem::remove(path);
  EXPECT_EQ(back.fx, camera.fx);
  EXPECT_EQ(back.distortion, camera.distortion);
  EXPECT_EQ(back.boresight_deg, camera.boresight_deg);
  // Undistort(Distort(p)) returns p within 1e-4 px across the image.
  for (double x : {0.0, 100.0, 319.5, 639.0}) {
    for (double y : {0.0, 255.5, 511.0}) {
      const Eigen::Vector2d p(x, y);
      EXPECT_LT((back.Undistort(back.Distort(p)) - p).norm(), 1e-4) << x << "," << y;
    }
  }
}

}  // namespace
}  // namespace irmosaic
