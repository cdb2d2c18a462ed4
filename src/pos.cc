#include "irmosaic/pos.h"

#include <GeographicLib/LocalCartesian.hpp>
#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <iomanip>
#include <map>
#include <sstream>

#include "irmosaic/error.h"

namespace irmosaic {
namespace {

constexpr double kDegToRad = M_PI / 180.0;

// Column name -> member of PosRecord, and whether the column is required.
struct ColumnSpec {
  const char* name;
  double PosRecord::*member;
  bool required;
  double min_value;
  double max_value;
  const char* range_text;
};

constexpr double kInf = std::numeric_limits<double>::infinity();

const std::vector<ColumnSpec>& Columns() {
  static const std::vector<ColumnSpec> columns = {
      {"time_s", &PosRecord::time_s, true, -kInf, kInf, "a finite number of seconds"},
      {"lat_deg", &PosRecord::lat_deg, true, -90.0, 90.0, "degrees in [-90, 90]"},
      {"lon_deg", &PosRecord::lon_deg, true, -180.0, 360.0, "degrees in [-180, 360]"},
      {"height_m", &PosRecord::height_m, true, -1000.0, 100000.0,
       "metres above the ellipsoid in [-1000, 100000]"},
      {"roll_deg", &PosRecord::roll_deg, true, -180.0, 180.0, "degrees in [-180, 180]"},
      {"pitch_deg", &PosRecord::pitch_deg, true, -90.0, 90.0, "degrees in [-90, 90]"},
      {"yaw_deg", &PosRecord::yaw_deg, true, -360.0, 360.0, "degrees in [-360, 360]"},
      {"gimbal_roll_deg", &PosRecord::gimbal_roll_deg, false, -180.0, 180.0,
       "degrees in [-180, 180]"},
      {"gimbal_pitch_deg", &PosRecord::gimbal_pitch_deg, false, -180.0, 180.0,
       "degrees in [-180, 180]"},
      {"gimbal_yaw_deg", &PosRecord::gimbal_yaw_deg, false, -360.0, 360.0,
       "degrees in [-360, 360]"},
  };
  return columns;
}

std::string ColumnList() {
  std::string text;
  for (const auto& c : Columns()) {
    if (!text.empty()) text += ",";
    text += c.name;
  }
  return text;
}

std::vector<std::string> SplitCsvLine(const std::string& line) {
  std::vector<std::string> fields;
  std::string field;
  std::istringstream stream(line);
  while (std::getline(stream, field, ',')) fields.push_back(field);
  if (!line.empty() && line.back() == ',') fields.emplace_back();
  return fields;
}

std::string Trim(const std::string& text) {
  const auto begin = text.find_first_not_of(" \t\r");
  if (begin == std::string::npos) return "";
  const auto end = text.find_last_not_of(" \t\r");
  return text.substr(begin, end - begin + 1);
}

void CheckValue(const ColumnSpec& spec, double value, const SourceLocation& where) {
  if (!std::isfinite(value)) {
    throw InputError(where, "value is not a finite number",
                     std::string("write ") + spec.range_text);
  }
  if (value < spec.min_value || value > spec.max_value) {
    std::ostringstream problem;
    problem << "value " << value << " is out of range";
    throw InputError(where, problem.str(), std::string("write ") + spec.range_text);
  }
}

void ValidateRecord(const PosRecord& r, const SourceLocation& row) {
  for (const ColumnSpec& spec : Columns()) {
    SourceLocation where = row;
    where.field = spec.name;
    CheckValue(spec, r.*(spec.member), where);
  }
}

void ValidateOrder(const std::vector<PosRecord>& records, const std::vector<SourceLocation>& rows) {
  for (size_t i = 1; i < records.size(); ++i) {
    if (!(records[i].time_s > records[i - 1].time_s)) {
      SourceLocation where = rows[i];
      where.field = "time_s";
      std::ostringstream problem;
      problem << "time " << std::setprecision(12) << records[i].time_s
              << (records[i].time_s == records[i - 1].time_s ? " repeats" : " goes back from")
              << " the previous record's " << records[i - 1].time_s;
      throw InputError(where, problem.str(), "sort the POS log by time and drop duplicate times");
    }
  }
}

}  // namespace

Eigen::Quaterniond RotationFromYpr(double yaw_deg, double pitch_deg, double roll_deg) {
  return Eigen::Quaterniond(Eigen::AngleAxisd(yaw_deg * kDegToRad, Eigen::Vector3d::UnitZ()) *
                            Eigen::AngleAxisd(pitch_deg * kDegToRad, Eigen::Vector3d::UnitY()) *
                            Eigen::AngleAxisd(roll_deg * kDegToRad, Eigen::Vector3d::UnitX()));
}

Pose PoseFromRecord(const PosRecord& r) {
  Pose pose;
  pose.lat_deg = r.lat_deg;
  pose.lon_deg = r.lon_deg;
  pose.height_m = r.height_m;
  pose.ned_from_body = RotationFromYpr(r.yaw_deg, r.pitch_deg, r.roll_deg);
  pose.body_from_mount = RotationFromYpr(r.gimbal_yaw_deg, r.gimbal_pitch_deg, r.gimbal_roll_deg);
  return pose;
}

PosTrack PosTrack::LoadCsv(const std::string& path, const Options& options) {
  std::ifstream in(path);
  if (!in) {
    throw InputError({path, 0, 0, ""}, "cannot open the POS file",
                     "check the path and that the file is readable");
  }
  std::string line;
  int line_number = 0;
  std::vector<int> column_of_field;  // For each CSV column, the index into Columns().
  bool have_header = false;
  std::vector<PosRecord> records;
  std::vector<SourceLocation> rows;
  while (std::getline(in, line)) {
    ++line_number;
    const std::string trimmed = Trim(line);
    if (trimmed.empty() || trimmed[0] == '#') continue;
    std::vector<std::string> fields = SplitCsvLine(trimmed);
    if (!have_header) {
      std::vector<bool> seen(Columns().size(), false);
      for (size_t i = 0; i < fields.size(); ++i) {
        const std::string name = Trim(fields[i]);
        auto it = std::find_if(Columns().begin(), Columns().end(),
                               [&](const ColumnSpec& c) { return name == c.name; });
        SourceLocation where{path, line_number, static_cast<int>(i + 1), name};
        if (it == Columns().end()) {
          throw InputError(where, "unknown column '" + name + "' in the header",
                           "use only the columns " + ColumnList() + " (docs/formats.md)");
        }
        const int index = static_cast<int>(it - Columns().begin());
        if (seen[index]) throw InputError(where, "column appears twice", "keep one of them");
        seen[index] = true;
        column_of_field.push_back(index);
      }
      for (size_t c = 0; c < Columns().size(); ++c) {
        if (Columns()[c].required && !seen[c]) {
          throw InputError(
              {path, line_number, 0, Columns()[c].name},
              std::string("the header lacks the required column '") + Columns()[c].name + "'",
              "the header must name at least time_s,lat_deg,lon_deg,height_m,"
              "roll_deg,pitch_deg,yaw_deg");
        }
      }
      have_header = true;
      continue;
    }
    if (fields.size() != column_of_field.size()) {
      std::ostringstream problem;
      problem << "row has " << fields.size() << " fields but the header has "
              << column_of_field.size();
      throw InputError({path, line_number, 0, ""}, problem.str(),
                       "give every row one value for each header column");
    }
    PosRecord record;
    for (size_t i = 0; i < fields.size(); ++i) {
      const ColumnSpec& spec = Columns()[column_of_field[i]];
      const std::string text = Trim(fields[i]);
      SourceLocation where{path, line_number, static_cast<int>(i + 1), spec.name};
      char* end = nullptr;
      errno = 0;
      const double value = std::strtod(text.c_str(), &end);
      if (text.empty() || end != text.c_str() + text.size()) {
        throw InputError(where, "'" + text + "' is not a number",
                         std::string("write ") + spec.range_text);
      }
      CheckValue(spec, value, where);
      record.*(spec.member) = value;
    }
    rows.push_back({path, line_number, 0, ""});
    records.push_back(record);
  }
  if (!have_header) {
    throw InputError({path, 0, 0, ""}, "the POS file is empty",
                     "write a header line (" + ColumnList() + ") and one row per sample");
  }
  if (records.empty()) {
    throw InputError({path, line_number, 0, ""}, "the POS file has a header but no records",
                     "add at least one POS row after the header");
  }
  ValidateOrder(records, rows);
  PosTrack track;
  track.records_ = std::move(records);
  track.options_ = options;
  return track;
}

PosTrack PosTrack::FromRecords(std::vector<PosRecord> records, const std::string& source,
                               const Options& options) {
  if (records.empty()) {
    throw InputError({source, 0, 0, ""}, "no POS records", "give at least one POS record");
  }
  std::vector<SourceLocation> rows;
  for (size_t i = 0; i < records.size(); ++i) {
    rows.push_back({source + " record " + std::to_string(i), 0, 0, ""});
    ValidateRecord(records[i], rows.back());
  }
  ValidateOrder(records, rows);
  PosTrack track;
  track.records_ = std::move(records);
  track.options_ = options;
  return track;
}

void PosTrack::WriteCsv(const std::string& path) const {
  std::ofstream out(path);
  if (!out) throw OutputError("cannot write the POS file " + path);
  out << ColumnList() << "\n";
  out << std::setprecision(17);
  for (const PosRecord& r : records_) {
    bool first = true;
    for (const ColumnSpec& c : Columns()) {
      out << (first ? "" : ",") << r.*(c.member);
      first = false;
    }
    out << "\n";
  }
  if (!out) throw OutputError("writing the POS file " + path + " failed (disk full?)");
}

PoseLookup PosTrack::At(double time_s) const {
  PoseLookup result;
  if (records_.empty() || !std::isfinite(time_s)) {
    result.status = PoseLookup::Status::kBeforeStart;
    result.message = "no POS for time " + std::to_string(time_s);
    return result;
  }
  constexpr double kTimeTolerance = 1e-9;
  if (time_s < records_.front().time_s - kTimeTolerance) {
    result.status = PoseLookup::Status::kBeforeStart;
    result.message = "time " + std::to_string(time_s) + " s is before the first POS record (" +
                     std::to_string(records_.front().time_s) + " s)";
    return result;
  }
  if (time_s > records_.back().time_s + kTimeTolerance) {
    result.status = PoseLookup::Status::kAfterEnd;
    result.message = "time " + std::to_string(time_s) + " s is after the last POS record (" +
                     std::to_string(records_.back().time_s) + " s)";
    return result;
  }
  // A time on a record (within tolerance) takes that record, even at the edge of a gap.
  auto nearest = std::lower_bound(records_.begin(), records_.end(), time_s - kTimeTolerance,
                                  [](const PosRecord& r, double t) { return r.time_s < t; });
  if (nearest != records_.end() && std::abs(nearest->time_s - time_s) <= kTimeTolerance) {
    result.pose = PoseFromRecord(*nearest);
    return result;
  }
  auto upper = std::upper_bound(records_.begin(), records_.end(), time_s,
                                [](double t, const PosRecord& r) { return t < r.time_s; });
  if (upper == records_.end()) upper = records_.end() - 1;
  if (upper == records_.begin())
    upper = records_.begin() + std::min<size_t>(1, records_.size() - 1);
  const PosRecord& a = *(upper == records_.begin() ? upper : upper - 1);
  const PosRecord& b = *upper;
  const double span = b.time_s - a.time_s;
  if (span <= 0.0) {  // Single record, time equal to it.
    result.pose = PoseFromRecord(a);
    return result;
  }
  if (span > options_.max_gap_s) {
    result.status = PoseLookup::Status::kInGap;
    result.message = "time " + std::to_string(time_s) + " s falls in a POS gap of " +
                     std::to_string(span) + " s (limit " + std::to_string(options_.max_gap_s) +
                     " s)";
    return result;
  }
  const double w = std::clamp((time_s - a.time_s) / span, 0.0, 1.0);
  const GeographicLib::LocalCartesian enu(a.lat_deg, a.lon_deg, a.height_m);
  double e = 0, n = 0, u = 0;
  enu.Forward(b.lat_deg, b.lon_deg, b.height_m, e, n, u);
  enu.Reverse(w * e, w * n, w * u, result.pose.lat_deg, result.pose.lon_deg, result.pose.height_m);
  const Pose pa = PoseFromRecord(a);
  const Pose pb = PoseFromRecord(b);
  result.pose.ned_from_body = pa.ned_from_body.slerp(w, pb.ned_from_body).normalized();
  result.pose.body_from_mount = pa.body_from_mount.slerp(w, pb.body_from_mount).normalized();
  return result;
}

}  // namespace irmosaic
