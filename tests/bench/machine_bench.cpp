// What this machine gives a second worker process, before any vispack code runs: three plain
// workloads, each timed alone (one child process) and two at once (two child processes released
// together), round after round, interleaved (alone, at once, alone, ...). The cluster chain's
// workers are processes, one per shard (tests/cluster/cluster_bench.sh), so this is the ceiling
// against which its "1 -> 2 workers" speed-up is read (docs/BENCHMARKS.md "Cluster"):
//   compute       a dependent integer loop in registers, no memory traffic: what two free
//                 cores give
//   fresh memory  first touch of --mib MiB of new anonymous memory, one write per 4 KiB page,
//                 then unmapped: the page faults every new process pays for its buffers. Before
//                 each timing the bench waits --settle-s seconds, so that memory freed by the
//                 previous one is as cold as a new process's (a VM with free page reporting
//                 hands freed pages back to its host after a few seconds)
//   memory read   passes over --mib MiB touched beforehand (not timed): memory bandwidth and
//                 the shared cache
// Prints one row per workload: the median time alone, the median of the slower of the two at
// once, the cost per worker at once, and the speed-up two workers could reach at best
// (2 x alone / at once). Exits 2 with a message on a bad argument, 1 when a child fails.
//   build/bin/machine_bench [--rounds R] [--mib M] [--compute-steps N] [--settle-s S]
//                           [--workers LIST]   (K processes at once for each K: 1 -> 2 -> 4 -> 8)
// bench-links: vispack_common
#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

namespace {

struct Options {
  int rounds = 3;
  std::size_t mib = 1024;
  std::int64_t compute_steps = 1'500'000'000;  // ~3 s on a 2-4 GHz core
  double settle_s = 3.0;
  std::vector<int> workers = {2};  // processes at once, each row timed against one alone
};

enum class Workload { kCompute, kFreshMemory, kMemoryRead };

double seconds_since(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

// The workload's timed part, in the calling (child) process; returns seconds, or < 0 on failure.
double run_workload(Workload workload, const Options& options) {
  const std::size_t bytes = options.mib << 20;
  const std::size_t page = 4096;
  if (workload == Workload::kCompute) {
    const auto start = std::chrono::steady_clock::now();
    std::uint64_t x = 88172645463325252ull;
    for (std::int64_t i = 0; i < options.compute_steps; ++i) {
      x ^= x << 13;
      x ^= x >> 7;
      x ^= x << 17;
    }
    const double s = seconds_since(start);
    return x == 0 ? -1.0 : s;  // xorshift never reaches 0: keeps the loop from being removed
  }
  void* map = mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
  if (map == MAP_FAILED) return -1.0;
  auto* p = static_cast<volatile unsigned char*>(map);
  double s = 0;
  if (workload == Workload::kFreshMemory) {
    const auto start = std::chrono::steady_clock::now();
    for (std::size_t i = 0; i < bytes; i += page)
      p[i] = 1;
    s = seconds_since(start);
  } else {
    for (std::size_t i = 0; i < bytes; i += page)
      p[i] = 1;
    const auto* words = static_cast<const std::uint64_t*>(map);
    std::uint64_t sum = 0;
    const auto start = std::chrono::steady_clock::now();
    for (int pass = 0; pass < 4; ++pass)
      for (std::size_t i = 0; i < bytes / 8; ++i)
        sum += words[i];
    s = seconds_since(start);
    if (sum != bytes / page * 4) s = -1.0;  // one 1 per page, four passes
  }
  munmap(map, bytes);
  return s;
}

// Runs the workload in `workers` child processes released together; returns each one's seconds
// (empty when a child failed).
std::vector<double> run_at_once(Workload workload, const Options& options, int workers) {
  int go[2], back[2];
  if (pipe(go) != 0) return {};
  if (pipe(back) != 0) {
    close(go[0]);
    close(go[1]);
    return {};
  }
  std::vector<pid_t> children;
  for (int w = 0; w < workers; ++w) {
    const pid_t pid = fork();
    if (pid < 0) break;
    if (pid == 0) {
      close(go[1]);
      close(back[0]);
      char byte = 0;
      if (read(go[0], &byte, 1) != 1) _exit(1);
      const double s = run_workload(workload, options);
      const bool written = write(back[1], &s, sizeof s) == ssize_t(sizeof s);
      _exit(written && s >= 0 ? 0 : 1);
    }
    children.push_back(pid);
  }
  close(go[0]);
  close(back[1]);
  const std::string release(children.size(), 'g');
  bool ok = int(children.size()) == workers &&
            write(go[1], release.data(), release.size()) == ssize_t(release.size());
  close(go[1]);
  std::vector<double> times;
  double s = 0;
  while (read(back[0], &s, sizeof s) == ssize_t(sizeof s))
    times.push_back(s);
  close(back[0]);
  for (pid_t pid : children) {
    int status = 0;
    ok = waitpid(pid, &status, 0) == pid && WIFEXITED(status) && WEXITSTATUS(status) == 0 && ok;
  }
  if (!ok || int(times.size()) != workers) return {};
  return times;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  const std::size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

[[noreturn]] void usage_error(const std::string& message) {
  std::fprintf(stderr, "machine_bench: %s\n", message.c_str());
  std::fprintf(stderr,
               "usage: machine_bench [--rounds R] [--mib M] [--compute-steps N] [--settle-s S] "
               "[--workers LIST]\n");
  std::exit(2);
}

double number_argument(int argc, char** argv, int& i, double low, double high) {
  const std::string flag = argv[i];
  if (i + 1 >= argc) usage_error(flag + " needs a value");
  char* end = nullptr;
  const double v = std::strtod(argv[++i], &end);
  if (end == argv[i] || *end != '\0' || !(v >= low && v <= high)) {
    char range[64];
    std::snprintf(range, sizeof range, "[%g, %g]", low, high);
    usage_error(flag + " '" + argv[i] + "': expected a number in " + range);
  }
  return v;
}

}  // namespace

int main(int argc, char** argv) {
  Options options;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--help" || arg == "-h") {
      std::printf(
          "usage: machine_bench [--rounds R] [--mib M] [--compute-steps N] [--settle-s S] "
          "[--workers LIST]\n"
          "Times a compute loop, the first touch of M MiB of fresh memory (after S s of rest) and\n"
          "read passes over M MiB, alone and K processes at once for each K of LIST (comma\n"
          "separated, each 2 to 1024), R interleaved rounds (defaults: 3 rounds, 1024 MiB, 1.5e9\n"
          "steps, 3 s, workers 2); prints what K workers get at best (K x alone / at once).\n");
      return 0;
    }
    if (arg == "--rounds") {
      options.rounds = int(number_argument(argc, argv, i, 1, 1000));
    } else if (arg == "--mib") {
      options.mib = std::size_t(number_argument(argc, argv, i, 1, 1 << 20));
    } else if (arg == "--compute-steps") {
      options.compute_steps = std::int64_t(number_argument(argc, argv, i, 1, 1e13));
    } else if (arg == "--settle-s") {
      options.settle_s = number_argument(argc, argv, i, 0, 3600);
    } else if (arg == "--workers") {
      if (i + 1 >= argc) usage_error("--workers needs a value");
      options.workers.clear();
      const std::string list = argv[++i];
      for (std::size_t pos = 0; pos <= list.size();) {
        std::size_t end = list.find(',', pos);
        if (end == std::string::npos) end = list.size();
        const std::string item = list.substr(pos, end - pos);
        char* stop = nullptr;
        const long k = std::strtol(item.c_str(), &stop, 10);
        if (item.empty() || *stop != '\0' || k < 2 || k > 1024)
          usage_error("--workers '" + list + "': expected a comma-separated list of 2 to 1024");
        options.workers.push_back(int(k));
        pos = end + 1;
      }
    } else {
      usage_error("unknown argument '" + arg + "'");
    }
  }

  struct Row {
    const char* name;
    Workload workload;
    std::vector<double> alone;
    std::vector<std::vector<double>> at_once;  // per entry of options.workers
  };
  const std::size_t counts = options.workers.size();
  std::vector<Row> rows = {{"compute", Workload::kCompute, {}, {}},
                           {"fresh memory", Workload::kFreshMemory, {}, {}},
                           {"memory read", Workload::kMemoryRead, {}, {}}};
  for (Row& row : rows)
    row.at_once.resize(counts);
  std::printf("machine: %u hardware threads; %d rounds, %zu MiB, %lld compute steps, %.1f s rest\n",
              std::thread::hardware_concurrency(), options.rounds, options.mib,
              static_cast<long long>(options.compute_steps), options.settle_s);
  for (int round = 0; round < options.rounds; ++round) {
    for (Row& row : rows) {
      for (std::size_t c = 0; c <= counts; ++c) {
        const int workers = c == 0 ? 1 : options.workers[c - 1];
        if (row.workload == Workload::kFreshMemory)
          std::this_thread::sleep_for(std::chrono::duration<double>(options.settle_s));
        const std::vector<double> times = run_at_once(row.workload, options, workers);
        if (times.empty()) {
          std::fprintf(stderr, "machine_bench: %s, %d worker(s), round %d: a child failed\n",
                       row.name, workers, round + 1);
          return 1;
        }
        const double slowest = *std::max_element(times.begin(), times.end());
        (c == 0 ? row.alone : row.at_once[c - 1]).push_back(slowest);
      }
    }
  }
  if (counts == 1 && options.workers[0] == 2) {
    // The table docs/BENCHMARKS.md "Cluster" quotes (tests/cluster/cluster_bench.sh prints it).
    std::printf(
        "| workload | alone, s | two at once, s (slower) | per worker at once | "
        "two workers at best |\n|---|---|---|---|---|\n");
    for (const Row& row : rows) {
      const double alone = median(row.alone), at_once = median(row.at_once[0]);
      std::printf("| %s | %.3f | %.3f | %+.0f %% | %.2fx |\n", row.name, alone, at_once,
                  100.0 * (at_once / alone - 1.0), 2.0 * alone / at_once);
    }
    return 0;
  }
  std::printf(
      "| workload | workers | alone, s | at once, s (slowest) | per worker at once | "
      "K workers at best |\n|---|---|---|---|---|---|\n");
  for (const Row& row : rows) {
    const double alone = median(row.alone);
    for (std::size_t c = 0; c < counts; ++c) {
      const int k = options.workers[c];
      const double at_once = median(row.at_once[c]);
      std::printf("| %s | %d | %.3f | %.3f | %+.0f %% | %.2fx |\n", row.name, k, alone, at_once,
                  100.0 * (at_once / alone - 1.0), double(k) * alone / at_once);
    }
  }
  return 0;
}
