#include "test_support.h"

#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <stdexcept>
#include <vector>

namespace vispack::test {
namespace {

int status_to_code(int status) {
  if (status == -1) return -1;
  if (WIFEXITED(status)) return WEXITSTATUS(status);
  return 128 + (WIFSIGNALED(status) ? WTERMSIG(status) : 0);
}

std::string slurp(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

}  // namespace

TempDir::TempDir(const std::string& prefix) {
  const char* tmp = std::getenv("TMPDIR");
  std::string pattern = std::string(tmp && *tmp ? tmp : "/tmp") + "/" + prefix + "-XXXXXX";
  if (!::mkdtemp(pattern.data())) throw std::runtime_error("mkdtemp failed for " + pattern);
  path_ = pattern;
}

TempDir::~TempDir() {
  if (std::getenv("VISPACK_KEEP_TEST_DIRS")) {
    std::cerr << "VISPACK_KEEP_TEST_DIRS: kept " << path_ << "\n";
    return;
  }
  std::error_code ec;
  std::filesystem::remove_all(path_, ec);
}

int run_command(const std::string& command, std::string* output) {
  std::string full = command + " 2>&1";
  FILE* pipe = ::popen(full.c_str(), "r");
  if (!pipe) return -1;
  std::array<char, 4096> buffer;
  std::string text;
  std::size_t n;
  while ((n = std::fread(buffer.data(), 1, buffer.size(), pipe)) > 0)
    text.append(buffer.data(), n);
  int status = ::pclose(pipe);
  if (output) *output = text;
  return status_to_code(status);
}

CommandResult run_command_split(const std::string& command) {
  TempDir dir("vispack-cmd");
  const std::string out = dir / "stdout", err = dir / "stderr";
  CommandResult r;
  r.code = status_to_code(std::system(("(" + command + ") >" + out + " 2>" + err).c_str()));
  r.out = slurp(out);
  r.err = slurp(err);
  return r;
}

std::string bin(const std::string& name) {
  return std::string(VISPACK_BIN_DIR) + "/" + name;
}

std::string source_dir() {
  return VISPACK_SOURCE_DIR;
}

double max_displacement_px(const RigidPx& a, const RigidPx& b, int width, int height) {
  const double cx = (width - 1) / 2.0, cy = (height - 1) / 2.0;
  auto map = [&](const RigidPx& t, double x, double y, double* px, double* py) {
    const double th = t.rotation_deg * M_PI / 180.0;
    const double c = std::cos(th), s = std::sin(th);
    *px = cx + c * (x - cx) - s * (y - cy) + t.dx;
    *py = cy + s * (x - cx) + c * (y - cy) + t.dy;
  };
  double worst = 0;
  const double xs[5] = {0, double(width - 1), 0, double(width - 1), cx};
  const double ys[5] = {0, 0, double(height - 1), double(height - 1), cy};
  for (int i = 0; i < 5; ++i) {
    double ax, ay, bx, by;
    map(a, xs[i], ys[i], &ax, &ay);
    map(b, xs[i], ys[i], &bx, &by);
    worst = std::max(worst, std::hypot(ax - bx, ay - by));
  }
  return worst;
}

double max_displacement_px(const SimilarityPx& a, const SimilarityPx& b, int ct_width,
                           int ct_height, int width, int height) {
  const double cx = (width - 1) / 2.0, cy = (height - 1) / 2.0;
  const double ux = (ct_width - 1) / 2.0, uy = (ct_height - 1) / 2.0;
  auto map = [&](const SimilarityPx& t, double x, double y, double* qx, double* qy) {
    const double th = t.rotation_deg * M_PI / 180.0;
    const double c = std::cos(th) * t.scale, s = std::sin(th) * t.scale;
    *qx = cx + c * (x - ux) - s * (y - uy) + t.dx;
    *qy = cy + s * (x - ux) + c * (y - uy) + t.dy;
  };
  double worst = 0;
  const double xs[5] = {0, double(ct_width - 1), 0, double(ct_width - 1), ux};
  const double ys[5] = {0, 0, double(ct_height - 1), double(ct_height - 1), uy};
  for (int i = 0; i < 5; ++i) {
    double ax, ay, bx, by;
    map(a, xs[i], ys[i], &ax, &ay);
    map(b, xs[i], ys[i], &bx, &by);
    worst = std::max(worst, std::hypot(ax - bx, ay - by));
  }
  return worst;
}

std::size_t resident_pages(const void* data, std::size_t size) {
  const std::size_t page = std::size_t(::sysconf(_SC_PAGESIZE));
  const std::size_t pages = (size + page - 1) / page;
  std::vector<unsigned char> in(pages);
  if (::mincore(const_cast<void*>(data), pages * page, in.data()) != 0)
    throw std::runtime_error(std::string("mincore failed: ") + std::strerror(errno));
  std::size_t n = 0;
  for (unsigned char c : in)
    n += c & 1;
  return n;
}

}  // namespace vispack::test
