// A test hook that stops a tool at a named point, so a test can change the world there (delete an
// input slice, say) at a moment it controls instead of after a guessed sleep. Inactive, and
// costing one cached getenv, unless the environment sets
//   VISPACK_TEST_PAUSE=<point>@<file>
// When the process reaches <point> it creates <file> and waits until the test removes it
// (polling every 5 ms; after 120 s it gives up and goes on, so a broken test cannot hang a run).
// Points named by the tools:
//   before:<stage>        vispack-run, before it starts that stage (register, mask, labels, ...)
//   done:<stage>:<k>      a pipeline stage has written and recorded slice k (StageRun::done)
//   append:pack:<k>       vispack-pack has handed slice k to the writer (the file is half written)
// A point is reached once per process at most: the pause fires the first time only.
#pragma once

#include <string>

namespace vispack {

// True when VISPACK_TEST_PAUSE is set (so callers can skip building the point's name).
bool test_pause_enabled();

// Pauses if `point` is the configured point (see above); otherwise returns at once.
void test_pause_point(const std::string& point);

}  // namespace vispack
