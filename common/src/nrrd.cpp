#include "vispack/common/nrrd.h"

#include <zlib.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <sstream>

#include "vispack/common/atomic_file.h"
#include "vispack/common/error.h"

namespace vispack {
namespace {

struct TypeName {
  NrrdType type;
  const char* name;
  std::size_t size;
};
const TypeName kTypes[] = {
    {NrrdType::kUint8, "uint8", 1},   {NrrdType::kInt8, "int8", 1},
    {NrrdType::kUint16, "uint16", 2}, {NrrdType::kInt16, "int16", 2},
    {NrrdType::kUint32, "uint32", 4}, {NrrdType::kInt32, "int32", 4},
    {NrrdType::kFloat32, "float", 4}, {NrrdType::kFloat64, "double", 8},
};

// Aliases that NRRD allows for the same type.
const std::map<std::string, NrrdType>& type_aliases() {
  static const std::map<std::string, NrrdType> aliases = {
      {"uchar", NrrdType::kUint8},      {"unsigned char", NrrdType::kUint8},
      {"uint8", NrrdType::kUint8},      {"uint8_t", NrrdType::kUint8},
      {"signed char", NrrdType::kInt8}, {"int8", NrrdType::kInt8},
      {"int8_t", NrrdType::kInt8},      {"short", NrrdType::kInt16},
      {"short int", NrrdType::kInt16},  {"signed short", NrrdType::kInt16},
      {"int16", NrrdType::kInt16},      {"int16_t", NrrdType::kInt16},
      {"ushort", NrrdType::kUint16},    {"unsigned short", NrrdType::kUint16},
      {"uint16", NrrdType::kUint16},    {"uint16_t", NrrdType::kUint16},
      {"int", NrrdType::kInt32},        {"int32", NrrdType::kInt32},
      {"int32_t", NrrdType::kInt32},    {"signed int", NrrdType::kInt32},
      {"uint", NrrdType::kUint32},      {"unsigned int", NrrdType::kUint32},
      {"uint32", NrrdType::kUint32},    {"uint32_t", NrrdType::kUint32},
      {"float", NrrdType::kFloat32},    {"double", NrrdType::kFloat64},
  };
  return aliases;
}

std::string trim(const std::string& s) {
  auto b = s.find_first_not_of(" \t\r");
  auto e = s.find_last_not_of(" \t\r");
  return b == std::string::npos ? std::string() : s.substr(b, e - b + 1);
}

std::string gzip_compress(const std::uint8_t* data, std::size_t size) {
  z_stream stream{};
  if (deflateInit2(&stream, 6, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY) != Z_OK) {
    throw Error("zlib: deflateInit2 failed");
  }
  std::string out;
  out.resize(deflateBound(&stream, uLong(size)) + 64);
  stream.next_in = const_cast<Bytef*>(data);
  stream.avail_in = uInt(size);
  stream.next_out = reinterpret_cast<Bytef*>(out.data());
  stream.avail_out = uInt(out.size());
  int rc = deflate(&stream, Z_FINISH);
  out.resize(stream.total_out);
  deflateEnd(&stream);
  if (rc != Z_STREAM_END) throw Error("zlib: deflate failed");
  return out;
}

void gzip_decompress(const std::string& path, const char* data, std::size_t size, std::uint8_t* out,
                     std::size_t out_size) {
  z_stream stream{};
  if (inflateInit2(&stream, 15 + 32) != Z_OK) throw Error("zlib: inflateInit2 failed");
  stream.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(data));
  stream.avail_in = uInt(size);
  stream.next_out = out;
  stream.avail_out = uInt(out_size);
  int rc = inflate(&stream, Z_FINISH);
  std::size_t produced = stream.total_out;
  inflateEnd(&stream);
  if (rc != Z_STREAM_END || produced != out_size) {
    throw FormatError(
        cat(path, ": gzip data is corrupt or holds ", produced, " bytes, expected ", out_size));
  }
}

}  // namespace

std::size_t nrrd_type_size(NrrdType type) {
  for (const auto& t : kTypes)
    if (t.type == type) return t.size;
  return 0;
}

const char* nrrd_type_name(NrrdType type) {
  for (const auto& t : kTypes)
    if (t.type == type) return t.name;
  return "unknown";
}

void write_nrrd(const std::string& path, const NrrdVolume& volume, bool gzip) {
  if (volume.data.size() != volume.byte_size()) {
    throw Error(cat(path, ": NRRD data holds ", volume.data.size(), " bytes, dims say ",
                    volume.byte_size()));
  }
  std::ostringstream header;
  header.precision(17);
  header << "NRRD0004\n# written by vispack\n";
  header << "type: " << nrrd_type_name(volume.type) << "\n";
  bool vector = volume.components > 1;
  header << "dimension: " << (vector ? 4 : 3) << "\n";
  header << "space dimension: 3\n";
  header << "sizes:";
  if (vector) header << " " << volume.components;
  for (auto d : volume.dims)
    header << " " << d;
  header << "\nspace directions:";
  if (vector) header << " none";
  for (int a = 0; a < 3; ++a) {
    header << " (";
    for (int b = 0; b < 3; ++b)
      header << (b ? "," : "") << (a == b ? volume.spacing_mm[a] : 0.0);
    header << ")";
  }
  header << "\nkinds:"
         << (vector ? (volume.components == 3   ? " RGB-color"
                       : volume.components == 4 ? " RGBA-color"
                                                : " vector")
                    : "")
         << " domain domain domain\n";
  header << "space units: \"mm\" \"mm\" \"mm\"\n";
  header << "space origin: (" << volume.origin_mm[0] << "," << volume.origin_mm[1] << ","
         << volume.origin_mm[2] << ")\n";
  if (nrrd_type_size(volume.type) > 1) header << "endian: little\n";
  header << "encoding: " << (gzip ? "gzip" : "raw") << "\n\n";
  AtomicFile file(path);
  file.write(header.str());
  if (gzip) {
    file.write(gzip_compress(volume.data.data(), volume.data.size()));
  } else {
    file.write(volume.data.data(), volume.data.size());
  }
  file.commit();
}

NrrdVolume read_nrrd(const std::string& path) {
  std::string bytes = read_file(path);
  if (bytes.compare(0, 4, "NRRD") != 0)
    throw FormatError(cat(path, ": not a NRRD file (no magic)"));
  std::size_t pos = bytes.find('\n');
  std::map<std::string, std::string> fields;
  for (;;) {
    if (pos == std::string::npos) throw FormatError(cat(path, ": NRRD header has no end"));
    std::size_t start = pos + 1;
    std::size_t end = bytes.find('\n', start);
    if (end == std::string::npos) throw FormatError(cat(path, ": NRRD header has no end"));
    std::string line = bytes.substr(start, end - start);
    pos = end;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty()) break;
    if (line[0] == '#') continue;
    auto colon = line.find(": ");
    if (colon == std::string::npos) {
      if (line.find(":=") != std::string::npos) continue;  // key/value comment
      throw FormatError(cat(path, ": bad NRRD header line '", line, "'"));
    }
    fields[trim(line.substr(0, colon))] = trim(line.substr(colon + 2));
  }
  std::size_t data_offset = pos + 1;
  auto need = [&](const char* key) -> const std::string& {
    auto it = fields.find(key);
    if (it == fields.end()) throw FormatError(cat(path, ": NRRD header lacks '", key, "'"));
    return it->second;
  };
  NrrdVolume volume;
  auto type_it = type_aliases().find(need("type"));
  if (type_it == type_aliases().end())
    throw FormatError(cat(path, ": unsupported NRRD type '", need("type"), "'"));
  volume.type = type_it->second;
  int dimension = std::atoi(need("dimension").c_str());
  if (dimension != 3 && dimension != 4)
    throw FormatError(cat(path, ": NRRD dimension ", dimension, " (need 3 or 4)"));
  std::istringstream sizes(need("sizes"));
  std::vector<long long> size_list;
  long long s;
  while (sizes >> s)
    size_list.push_back(s);
  if (int(size_list.size()) != dimension)
    throw FormatError(cat(path, ": NRRD sizes do not match dimension"));
  std::size_t total = nrrd_type_size(volume.type);
  for (long long v : size_list) {
    if (v <= 0 || v > (1LL << 31)) throw FormatError(cat(path, ": NRRD size ", v, " out of range"));
    if (total > std::numeric_limits<std::size_t>::max() / std::size_t(v))
      throw FormatError(cat(path, ": NRRD sizes overflow"));
    total *= std::size_t(v);
  }
  int axis0 = 0;
  if (dimension == 4) {
    if (size_list[0] > 4)
      throw FormatError(cat(path, ": NRRD first axis of ", size_list[0], " components (max 4)"));
    volume.components = int(size_list[0]);
    axis0 = 1;
  }
  for (int a = 0; a < 3; ++a)
    volume.dims[a] = size_list[axis0 + a];
  // Spacing: "space directions" (diagonal taken as norm of each vector) or "spacings".
  if (fields.count("space directions")) {
    std::string text = fields["space directions"];
    int axis = 0;
    std::size_t p = 0;
    while (axis < 3 && (p = text.find('(', p)) != std::string::npos) {
      std::size_t q = text.find(')', p);
      if (q == std::string::npos) break;
      std::string vec = text.substr(p + 1, q - p - 1);
      std::replace(vec.begin(), vec.end(), ',', ' ');
      std::istringstream in(vec);
      double x = 0, y = 0, z = 0;
      in >> x >> y >> z;
      volume.spacing_mm[axis++] = std::sqrt(x * x + y * y + z * z);
      p = q + 1;
    }
  } else if (fields.count("spacings")) {
    std::istringstream in(fields["spacings"]);
    std::string token;
    std::vector<double> values;
    while (in >> token)
      values.push_back(token == "nan" ? 1.0 : std::atof(token.c_str()));
    for (int a = 0; a < 3 && axis0 + a < int(values.size()); ++a)
      volume.spacing_mm[a] = values[axis0 + a];
  }
  if (fields.count("space origin")) {
    std::string text = fields["space origin"];
    std::replace(text.begin(), text.end(), '(', ' ');
    std::replace(text.begin(), text.end(), ')', ' ');
    std::replace(text.begin(), text.end(), ',', ' ');
    std::istringstream in(text);
    in >> volume.origin_mm[0] >> volume.origin_mm[1] >> volume.origin_mm[2];
  }
  std::string encoding = need("encoding");
  volume.data.resize(total);
  if (encoding == "raw") {
    if (bytes.size() - data_offset < total) {
      throw FormatError(cat(path, ": NRRD data is truncated: ", bytes.size() - data_offset,
                            " bytes, expected ", total));
    }
    std::memcpy(volume.data.data(), bytes.data() + data_offset, total);
  } else if (encoding == "gzip" || encoding == "gz") {
    gzip_decompress(path, bytes.data() + data_offset, bytes.size() - data_offset,
                    volume.data.data(), total);
  } else {
    throw FormatError(cat(path, ": unsupported NRRD encoding '", encoding, "'"));
  }
  std::size_t scalar = nrrd_type_size(volume.type);
  if (scalar > 1 && fields.count("endian") && fields["endian"] == "big") {
    for (std::size_t i = 0; i < total; i += scalar)
      std::reverse(&volume.data[i], &volume.data[i] + scalar);
  }
  return volume;
}

}  // namespace vispack
