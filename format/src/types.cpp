#include "vispack/format/types.h"

#include <stdexcept>

namespace vispack::format {

std::size_t channel_type_bytes(ChannelType type) {
  switch (type) {
    case ChannelType::kRgba8:
      return 4;
    case ChannelType::kInt16:
      return 2;
    case ChannelType::kUint8:
      return 1;
    case ChannelType::kUint16:
      return 2;
  }
  throw std::invalid_argument(cat("unknown channel type ", int(type)));
}

int channel_type_components(ChannelType type) {
  return type == ChannelType::kRgba8 ? 4 : 1;
}

const char* channel_type_name(ChannelType type) {
  switch (type) {
    case ChannelType::kRgba8:
      return "rgba8";
    case ChannelType::kInt16:
      return "int16";
    case ChannelType::kUint8:
      return "uint8";
    case ChannelType::kUint16:
      return "uint16";
  }
  throw std::invalid_argument(cat("unknown channel type ", int(type)));
}

ChannelType channel_type_from_name(const std::string& name) {
  if (name == "rgba8") return ChannelType::kRgba8;
  if (name == "int16") return ChannelType::kInt16;
  if (name == "uint8") return ChannelType::kUint8;
  if (name == "uint16") return ChannelType::kUint16;
  throw FormatError(cat("unknown channel type \"", name, "\""));
}

const char* codec_name(Codec codec) {
  switch (codec) {
    case Codec::kUniform:
      return "uniform";
    case Codec::kRaw:
      return "raw";
    case Codec::kZstd:
      return "zstd";
  }
  return "unknown";
}

}  // namespace vispack::format
