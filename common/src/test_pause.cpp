#include "vispack/common/test_pause.h"

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <thread>

namespace vispack {
namespace {

struct PauseSetting {
  std::string point, file;
};

const PauseSetting& setting() {
  static const PauseSetting s = [] {
    PauseSetting r;
    const char* value = std::getenv("VISPACK_TEST_PAUSE");
    if (!value) return r;
    const std::string text(value);
    const auto at = text.rfind('@');
    if (at == std::string::npos || at == 0 || at + 1 == text.size()) return r;
    r.point = text.substr(0, at);
    r.file = text.substr(at + 1);
    return r;
  }();
  return s;
}

}  // namespace

bool test_pause_enabled() {
  return !setting().point.empty();
}

void test_pause_point(const std::string& point) {
  const PauseSetting& s = setting();
  if (s.point.empty() || point != s.point) return;
  static std::atomic<bool> fired{false};
  if (fired.exchange(true)) return;
  namespace fs = std::filesystem;
  std::ofstream(s.file) << point << "\n";
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  std::error_code ec;
  while (fs::exists(s.file, ec) && std::chrono::steady_clock::now() < give_up)
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
}

}  // namespace vispack
