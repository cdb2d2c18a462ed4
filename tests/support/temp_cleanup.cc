// Linked into every test program: when all of the program's tests passed, removes the scratch
// files and folders its tests made in the temporary folder (names starting "irmosaic_" that
// hold this process's id as one of their '_'- or '.'-separated parts, as the tests name them);
// after a failure it keeps them and says where, for a look at what the failing test wrote.
// Without it every ctest run left its stores behind (~930 entries after a day of runs).
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <iostream>
#include <string>
#include <system_error>
#include <vector>

namespace {

namespace fs = std::filesystem;

bool NamedForThisProcess(const std::string& name, const std::string& pid) {
  if (name.rfind("irmosaic_", 0) != 0) return false;
  size_t start = 0;
  while (start <= name.size()) {
    const size_t end = name.find_first_of("_.", start);
    const size_t stop = end == std::string::npos ? name.size() : end;
    if (name.compare(start, stop - start, pid) == 0 && stop - start == pid.size()) return true;
    if (end == std::string::npos) break;
    start = end + 1;
  }
  return false;
}

class TempCleanup : public ::testing::Environment {
 public:
  void TearDown() override {
    const std::string pid = std::to_string(::getpid());
    std::error_code error;
    std::vector<fs::path> ours;
    for (const auto& entry : fs::directory_iterator(fs::temp_directory_path(error), error)) {
      if (NamedForThisProcess(entry.path().filename().string(), pid)) ours.push_back(entry.path());
    }
    if (ours.empty()) return;
    if (::testing::UnitTest::GetInstance()->Failed()) {
      std::cerr << "temp_cleanup: a test failed; kept its files:";
      for (const fs::path& path : ours) std::cerr << ' ' << path.string();
      std::cerr << '\n';
      return;
    }
    for (const fs::path& path : ours) fs::remove_all(path, error);
  }
};

[[maybe_unused]] ::testing::Environment* const kTempCleanup =
    ::testing::AddGlobalTestEnvironment(new TempCleanup);

}  // namespace
