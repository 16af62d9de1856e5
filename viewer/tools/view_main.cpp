// vispack-view FILE [--screenshot OUT.png --size WxH] [--mode M] [...]: the volume viewer.
#include "vispack/common/cli.h"
#include "vispack/viewer/app.h"

int main(int argc, char** argv) {
  return vispack::run_main("vispack-view", argc, argv, [](vispack::Args& args) {
    vispack::viewer::ViewOptions options = vispack::viewer::parse_view_options(args);
    if (!options.screenshot.empty()) return vispack::viewer::run_screenshot(options);
    return vispack::viewer::run_window(options);
  });
}
