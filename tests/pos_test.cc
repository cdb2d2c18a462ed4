// POS log parsing, validation and interpolation.
#include "irmosaic/pos.h"

#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

#include "irmosaic/error.h"
#include "irmosaic/local_frame.h"

namespace irmosaic {
namespace {

const char* kHeader = "time_s,lat_deg,lon_deg,height_m,roll_deg,pitch_deg,yaw_deg\n";

std::string WriteTemp(const std::string& name, const std::string& text) {
  const auto path = std::filesystem::temp_directory_path() /
                    ("irmosaic_pos_test_" + std::to_string(::getpid()) + "_" + name);
  std::ofstream(path) << text;
  return path.string();
}

// Loads `text` and returns the InputError's message (fails the test if none is thrown).
std::string ErrorOf(const std::string& name, const std::string& text) {
  const std::string path = WriteTemp(name, text);
  try {
    PosTrack::LoadCsv(path);
  } catch (const InputError& e) {
    std::filesystem::remove(path);
    return e.what();
  }
  std::filesystem::remove(path);
  ADD_FAILURE() << "no error for " << name;
  return "";
}

TEST(PosTest, BadInputNamesFileLineAndField) {
  struct Case {
    const char* name;
    std::string text;
    std::string expect_place;  // Must appear in the message.
    std::string expect_word;
  };
  const std::vector<Case> cases = {
      {"empty.csv", "", "empty.csv", "empty"},
      {"header_only.csv", kHeader, "header_only.csv:1", "no records"},
      {"nan.csv", std::string(kHeader) + "0,47,8,500,0,0,0\n1,nan,8,500,0,0,0\n", ":3:2",
       "lat_deg"},
      {"inf.csv", std::string(kHeader) + "0,47,8,inf,0,0,0\n", ":2:4", "height_m"},
      {"lat_range.csv", std::string(kHeader) + "0,91.5,8,500,0,0,0\n", ":2:2", "out of range"},
      {"time_back.csv",
       std::string(kHeader) + "0,47,8,500,0,0,0\n2,47,8,500,0,0,0\n"
                              "1,47,8,500,0,0,0\n",
       ":4", "goes back"},
      {"time_dup.csv", std::string(kHeader) + "0,47,8,500,0,0,0\n0,47,8,500,0,0,0\n", ":3",
       "repeats"},
      {"columns.csv", std::string(kHeader) + "0,47,8,500,0,0\n", ":2", "6 fields"},
      {"unknown.csv", "time_s,lat_deg,lon_deg,height_m,roll_deg,pitch_deg,yaw_deg,speed\n", ":1:8",
       "unknown column 'speed'"},
      {"missing.csv", "time_s,lat_deg,lon_deg,height_m,roll_deg,pitch_deg\n", "yaw_deg",
       "lacks the required column"},
      {"text.csv", std::string(kHeader) + "0,47,8,500,0,abc,0\n", ":2:6", "not a number"},
  };
  for (const Case& c : cases) {
    const std::string message = ErrorOf(c.name, c.text);
    EXPECT_NE(message.find(c.expect_place), std::string::npos) << c.name << ": " << message;
    EXPECT_NE(message.find(c.expect_word), std::string::npos) << c.name << ": " << message;
    EXPECT_NE(message.find("Fix:"), std::string::npos) << c.name << ": " << message;
  }
}

TEST(PosTest, MissingFileIsAnInputError) {
  EXPECT_THROW(PosTrack::LoadCsv("/nonexistent/pos.csv"), InputError);
}

TEST(PosTest, InterpolatesPositionInEnuAndAttitudeBySlerp) {
  const std::string path =
      WriteTemp("ok.csv",
                "# comment line\n"
                "time_s,lat_deg,lon_deg,height_m,roll_deg,pitch_deg,yaw_deg,gimbal_roll_deg\n"
                "10.0,47.0,8.0,500,0,0,10,-20\n10.2,47.001,8.0,520,0,0,20,20\n");
  const PosTrack track = PosTrack::LoadCsv(path);
  std::filesystem::remove(path);
  const PoseLookup mid = track.At(10.1);
  ASSERT_TRUE(mid.ok()) << mid.message;
  const LocalFrame frame(47.0, 8.0);
  const Eigen::Vector3d a = frame.EnuFromGeodetic(47.0, 8.0, 500);
  const Eigen::Vector3d b = frame.EnuFromGeodetic(47.001, 8.0, 520);
  const Eigen::Vector3d m =
      frame.EnuFromGeodetic(mid.pose.lat_deg, mid.pose.lon_deg, mid.pose.height_m);
  EXPECT_LT((m - 0.5 * (a + b)).norm(), 0.01);  // Midpoint within 1 cm.
  // Yaw 15 deg, gimbal roll 0 at the midpoint (slerp of a pure-axis rotation).
  const Eigen::Quaterniond yaw15 = RotationFromYpr(15.0, 0, 0);
  EXPECT_LT(mid.pose.ned_from_body.angularDistance(yaw15) * 180 / M_PI, 1e-6);
  EXPECT_LT(mid.pose.body_from_mount.angularDistance(Eigen::Quaterniond::Identity()) * 180 / M_PI,
            1e-6);
}

TEST(PosTest, OutsideRangeAndGapsAreReportedNotExtrapolated) {
  std::vector<PosRecord> records(3);
  records[0].time_s = 0.0;
  records[1].time_s = 0.5;
  records[2].time_s = 5.0;  // A 4.5 s gap.
  for (auto& r : records) {
    r.lat_deg = 47;
    r.lon_deg = 8;
    r.height_m = 500;
  }
  PosTrack::Options options;
  options.max_gap_s = 1.0;
  const PosTrack track = PosTrack::FromRecords(records, "test", options);
  EXPECT_EQ(track.At(-0.01).status, PoseLookup::Status::kBeforeStart);
  EXPECT_EQ(track.At(5.01).status, PoseLookup::Status::kAfterEnd);
  EXPECT_EQ(track.At(2.0).status, PoseLookup::Status::kInGap);
  EXPECT_NE(track.At(2.0).message.find("gap"), std::string::npos);
  EXPECT_TRUE(track.At(0.25).ok());
  EXPECT_TRUE(track.At(5.0).ok());
  EXPECT_TRUE(track.At(0.0).ok());
}

TEST(PosTest, WriteThenLoadIsExact) {
  std::vector<PosRecord> records(2);
  records[0] = {1.25, 47.123456789012, 8.98765432101, 512.5, 1.5, -2.5, 359.0, 10, 2, 0};
  records[1] = {1.29, 47.123466789012, 8.98765432101, 512.7, 1.4, -2.4, 358.0, 12, 2, 0};
  const PosTrack track = PosTrack::FromRecords(records, "test", {});
  const std::string path = WriteTemp("roundtrip.csv", "");
  track.WriteCsv(path);
  const PosTrack back = PosTrack::LoadCsv(path);
  std::filesystem::remove(path);
  ASSERT_EQ(back.records().size(), 2u);
  EXPECT_EQ(back.records()[1].lat_deg, records[1].lat_deg);
  EXPECT_EQ(back.records()[0].gimbal_roll_deg, 10.0);
}

}  // namespace
}  // namespace irmosaic
