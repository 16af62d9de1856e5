// The cost of touching fresh anonymous memory on this machine (docs/BENCHMARKS.md "Fresh memory
// on this machine, and the pack encoder's first slab"): wall and CPU seconds (user + system, the
// process's) of a memset over newly mapped memory. A benchmark helper, not part of the build:
//   cc -O2 -pthread scripts/bench/fresh_touch.c -o fresh_touch
//   fresh_touch once MIB [THREADS] [huge]  map MIB MiB (MADV_HUGEPAGE with "huge"), memset it on
//                                          THREADS threads (a part each), print, unmap
//   fresh_touch chain MIB N [huge]         map and memset MIB MiB N times, all held; one line each
// Run it back to back, or after some seconds of rest, to see what free page reporting costs
// (memory freed moments before against memory the host has taken back).
#define _GNU_SOURCE
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <time.h>

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}
// CPU seconds (user + system) of this process so far, all threads.
static double cpu(void) {
  struct rusage u;
  getrusage(RUSAGE_SELF, &u);
  return u.ru_utime.tv_sec + u.ru_stime.tv_sec + 1e-6 * (u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}
struct part { char* p; size_t n; };
static void* fill(void* a) { struct part* q = a; memset(q->p, 1, q->n); return 0; }
static char* map(size_t n, int huge) {
  char* p = mmap(0, n, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
  if (p == MAP_FAILED) { perror("mmap"); exit(1); }
  if (huge && madvise(p, n, MADV_HUGEPAGE)) { perror("madvise"); exit(1); }
  return p;
}
int main(int argc, char** argv) {
  if (argc < 3 || (strcmp(argv[1], "once") && strcmp(argv[1], "chain")) || atol(argv[2]) <= 0) {
    fprintf(stderr, "usage: fresh_touch once MIB [THREADS] [huge] | chain MIB N [huge]\n");
    return 2;
  }
  size_t n = (size_t)atol(argv[2]) << 20;
  if (!strcmp(argv[1], "once")) {
    int threads = argc > 3 ? atoi(argv[3]) : 1, huge = argc > 4 && !strcmp(argv[4], "huge");
    if (threads < 1 || threads > 16) {
      fprintf(stderr, "fresh_touch: THREADS must be 1..16, not %s\n", argv[3]);
      return 2;
    }
    char* p = map(n, huge);
    pthread_t th[16]; struct part parts[16];
    double t0 = now(), c0 = cpu();
    for (int i = 0; i < threads; ++i) {
      parts[i].p = p + n / threads * i; parts[i].n = n / threads;
      pthread_create(&th[i], 0, fill, &parts[i]);
    }
    for (int i = 0; i < threads; ++i) pthread_join(th[i], 0);
    printf("once %zu MiB threads %d%s: %.3f s wall, %.3f s CPU\n", n >> 20, threads, huge ? " huge" : "",
           now() - t0, cpu() - c0);
    munmap(p, n);
  } else {
    int count = atoi(argv[3]), huge = argc > 4 && !strcmp(argv[4], "huge");
    for (int i = 0; i < count; ++i) {
      char* p = map(n, huge);
      double t0 = now(), c0 = cpu();
      memset(p, 1, n);
      printf("chain %d/%d %zu MiB%s: %.3f s wall, %.3f s CPU\n", i + 1, count, n >> 20, huge ? " huge" : "",
             now() - t0, cpu() - c0);
      fflush(stdout);
    }
  }
  return 0;
}
