// Point files of other sensors (engine/data/point_formats.hpp) and the input mapping
// (engine/data/input_mapping.hpp): every format and variant written here by hand with known
// values and read back; malformed files of each kind with their messages; the real KITTI scan
// converted to .npy, .pcd and .ply and read back identically; sequences of any format; the
// mapping by hand, from a run config, in a sequence's poses and in the segmenter.
#include <fmt/format.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <bit>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <numbers>
#include <string>
#include <vector>

#include "core/io.hpp"
#include "engine/data/input_mapping.hpp"
#include "engine/data/point_formats.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/run_config.hpp"
#include "engine/pipeline/dataset.hpp"
#include "engine/pipeline/segmenter.hpp"
#include "tests/support/scans.hpp"
#include "tests/support/test_support.hpp"
#include "tests/support/tiny_model.hpp"

using namespace pillarseg;
namespace fs = std::filesystem;
using pillarseg::test::error_of;
using ::testing::HasSubstr;

namespace {

const std::vector<Point> kPoints = {{1.5f, -2.25f, 0.125f, 0.5f}, {-30.0f, 12.5f, -1.75f, 0.25f}, {0, 0, 3, 1}};

// Bytes of values, little- or big-endian.
class Bytes {
 public:
  template <class T>
  Bytes& put(T v, bool big_endian = false) {
    char raw[sizeof(T)];
    std::memcpy(raw, &v, sizeof(T));
    if (big_endian) std::reverse(raw, raw + sizeof(T));
    text.append(raw, sizeof(T));
    return *this;
  }
  Bytes& put_text(const std::string& s) {
    text += s;
    return *this;
  }
  std::string text;
};

fs::path write(const fs::path& path, const std::string& bytes) {
  fs::create_directories(path.parent_path());
  std::ofstream(path, std::ios::binary).write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  return path;
}

// A .npy file: the magic, version, header length, the dict padded to 64 bytes with '\n' last.
std::string npy(const std::string& descr, const std::string& shape, const std::string& data, int major = 1,
                const std::string& order = "False") {
  std::string dict = "{'descr': '" + descr + "', 'fortran_order': " + order + ", 'shape': " + shape + ", }";
  const size_t preamble = major == 1 ? 10 : 12;
  while ((preamble + dict.size() + 1) % 64 != 0) dict += ' ';
  dict += '\n';
  Bytes b;
  b.put_text("\x93NUMPY").put<uint8_t>(static_cast<uint8_t>(major)).put<uint8_t>(0);
  if (major == 1) b.put<uint16_t>(static_cast<uint16_t>(dict.size()));
  else b.put<uint32_t>(static_cast<uint32_t>(dict.size()));
  return b.text + dict + data;
}

void expect_points(const std::vector<Point>& got, const std::vector<Point>& expected) {
  ASSERT_EQ(got.size(), expected.size());
  for (size_t i = 0; i < got.size(); ++i) {
    SCOPED_TRACE(::testing::Message() << "point " << i);
    EXPECT_EQ(got[i].x, expected[i].x);
    EXPECT_EQ(got[i].y, expected[i].y);
    EXPECT_EQ(got[i].z, expected[i].z);
    EXPECT_EQ(got[i].r, expected[i].r);
  }
}

bool same_bits(const std::vector<Point>& a, const std::vector<Point>& b) {
  return a.size() == b.size() && (a.empty() || std::memcmp(a.data(), b.data(), a.size() * sizeof(Point)) == 0);
}

}  // namespace

TEST(PointFormats, NamesAndExtensions) {
  EXPECT_EQ(parse_point_format("npy"), PointFormat::Npy);
  EXPECT_EQ(parse_point_format("nuscenes"), PointFormat::Nuscenes);
  EXPECT_EQ(parse_point_format("auto"), PointFormat::FromExtension);
  EXPECT_THAT(error_of([] { parse_point_format("las"); }),
              HasSubstr("--format 'las': unknown point format (expected auto, kitti, pcd, ply, npy or nuscenes)"));
  EXPECT_EQ(point_format_of("a/000001.bin"), PointFormat::Kitti);
  EXPECT_EQ(point_format_of("n015-2018__LIDAR_TOP__1.pcd.bin"), PointFormat::Nuscenes);
  EXPECT_EQ(point_format_of("scan.PCD"), PointFormat::Pcd);
  EXPECT_EQ(point_format_of("scan.ply"), PointFormat::Ply);
  EXPECT_EQ(point_format_of("scan.npy"), PointFormat::Npy);
  EXPECT_THAT(error_of([] { point_format_of("scan.xyz"); }),
              HasSubstr("scan.xyz: no point-file extension (.bin KITTI, .pcd, .ply, .npy, .pcd.bin nuScenes)"));
  EXPECT_THAT(error_of([] { point_format_of(".bin"); }), HasSubstr("no point-file extension"));
}

TEST(PointFormats, KittiThroughReadPointsIsReadScan) {
  const fs::path dir = test::temp_dir();
  std::vector<Point> points = kPoints;
  points.insert(points.begin() + 1, Point{std::numeric_limits<float>::quiet_NaN(), 0, 0, 0});
  write_bin(dir / "000000.bin", points);
  write_labels(dir / "000000.label", {10, 99, 40, 252});
  const Scan a = read_points(dir / "000000.bin", PointFormat::FromExtension, dir / "000000.label");
  const Scan b = read_scan(dir / "000000.bin", dir / "000000.label");
  expect_points(a.points, kPoints);
  EXPECT_TRUE(same_bits(a.points, b.points));
  EXPECT_EQ(a.labels, (std::vector<uint32_t>{10, 40, 252}));
  EXPECT_EQ(a.labels, b.labels);
  EXPECT_EQ(a.dropped_nonfinite, 1u);
  // Another format's labels: the count must be the file's, dropped points and all.
  write_labels(dir / "three.label", {1, 2, 3});
  EXPECT_THAT(error_of([&] { read_points(dir / "000000.bin", PointFormat::Kitti, dir / "three.label"); }),
              HasSubstr("three.label: 3 labels, but " + (dir / "000000.bin").string() + " has 4 points"));
}

TEST(PointFormats, Npy) {
  const fs::path dir = test::temp_dir();
  Bytes f32x4, f64x3, be_f32x5;
  for (const Point& p : kPoints) {
    f32x4.put(p.x).put(p.y).put(p.z).put(p.r);
    f64x3.put(static_cast<double>(p.x)).put(static_cast<double>(p.y)).put(static_cast<double>(p.z));
    be_f32x5.put(p.x, true).put(p.y, true).put(p.z, true).put(p.r, true).put(7.0f, true);
  }
  expect_points(read_points(write(dir / "a.npy", npy("<f4", "(3, 4)", f32x4.text))).points, kPoints);
  std::vector<Point> no_reflectance = kPoints;
  for (Point& p : no_reflectance) p.r = 0;
  expect_points(read_points(write(dir / "b.npy", npy("<f8", "(3, 3)", f64x3.text, 2))).points, no_reflectance);
  expect_points(read_points(write(dir / "c.npy", npy(">f4", "(3, 5)", be_f32x5.text, 3))).points, kPoints);
  EXPECT_TRUE(read_points(write(dir / "empty.npy", npy("<f4", "(0, 4)", ""))).points.empty());
  // Float64 values round to float32 once.
  Bytes precise;
  precise.put(0.1).put(-1e-3).put(1.0 / 3.0).put(255.0);
  expect_points(read_points(write(dir / "d.npy", npy("<f8", "(1, 4)", precise.text))).points,
                {{0.1f, -1e-3f, static_cast<float>(1.0 / 3.0), 255.0f}});
}

TEST(PointFormats, NuscenesPcdBin) {
  const fs::path dir = test::temp_dir();
  Bytes b;
  for (size_t i = 0; i < kPoints.size(); ++i)
    b.put(kPoints[i].x).put(kPoints[i].y).put(kPoints[i].z).put(kPoints[i].r * 255).put(static_cast<float>(i * 10));
  std::vector<Point> expected = kPoints;
  for (Point& p : expected) p.r *= 255;
  const fs::path path = write(dir / "n008__LIDAR_TOP__1533151603547590.pcd.bin", b.text);
  expect_points(read_points(path).points, expected);
  expect_points(read_points(write(dir / "renamed.dat", b.text), PointFormat::Nuscenes).points, expected);
}

TEST(PointFormats, PcdAsciiFieldsInAnyOrder) {
  const fs::path dir = test::temp_dir();
  // y before x, an unsigned 8-bit reflectance, a field of three values in the middle, a NaN point.
  const std::string pcd =
      "# .PCD v0.7 - Point Cloud Data file format\n"
      "VERSION 0.7\n"
      "FIELDS y normal x reflectance z\n"
      "SIZE 4 4 8 1 4\n"
      "TYPE F F F U F\n"
      "COUNT 1 3 1 1 1\n"
      "WIDTH 4\n"
      "HEIGHT 1\n"
      "VIEWPOINT 0 0 0 1 0 0 0\n"
      "POINTS 4\n"
      "DATA ascii\n"
      "-2.25 0 0 1 1.5 128 0.125\n"
      "12.5 0.5 0.5 0.5 -30 64 -1.75\r\n"
      "nan nan nan nan nan 0 nan\n"
      "0 1 0 0 0 255 3\n";
  const Scan scan = read_points(write(dir / "a.pcd", pcd));
  expect_points(scan.points, {{1.5f, -2.25f, 0.125f, 128}, {-30, 12.5f, -1.75f, 64}, {0, 0, 3, 255}});
  EXPECT_EQ(scan.dropped_nonfinite, 1u);
}

TEST(PointFormats, PcdBinaryWithPaddingCountsAndIntegerIntensity) {
  const fs::path dir = test::temp_dir();
  // normal (3 x float32), z (float64), 3 padding bytes, intensity (uint16), x, y (float32).
  Bytes b;
  b.put_text(
      "FIELDS normal z _ intensity x y\nSIZE 4 8 1 2 4 4\nTYPE F F U U F F\nCOUNT 3 1 3 1 1 1\nWIDTH 3\nHEIGHT 1\n"
      "POINTS 3\nDATA binary\n");
  const uint16_t intensity[] = {500, 0, 65535};
  for (size_t i = 0; i < kPoints.size(); ++i) {
    const Point& p = kPoints[i];
    b.put(9.0f).put(9.0f).put(9.0f).put(static_cast<double>(p.z)).put<uint8_t>(0xAB).put<uint8_t>(0xCD);
    b.put<uint8_t>(0xEF).put(intensity[i]).put(p.x).put(p.y);
  }
  expect_points(read_points(write(dir / "a.pcd", b.text)).points,
                {{1.5f, -2.25f, 0.125f, 500}, {-30, 12.5f, -1.75f, 0}, {0, 0, 3, 65535}});
  // The intensity's name may be 'i', a signed 8-bit value.
  Bytes c;
  c.put_text("FIELDS x y z i\nSIZE 4 4 4 1\nTYPE F F F I\nWIDTH 1\nPOINTS 1\nDATA binary\n");
  c.put(1.0f).put(2.0f).put(3.0f).put<int8_t>(-5);
  expect_points(read_points(write(dir / "b.pcd", c.text)).points, {{1, 2, 3, -5}});
  // No intensity field: reflectance 0.
  Bytes d;
  d.put_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary\n");
  d.put(1.0f).put(2.0f).put(3.0f);
  expect_points(read_points(write(dir / "c.pcd", d.text)).points, {{1, 2, 3, 0}});
}

// binary_compressed: the fields one after another (x of every point, then y, ...), LZF-compressed.
// The LZF stream is written by hand: literal runs, a short back-reference (length 3 bits) and a
// long one (length 7 + a byte), each pointing into the bytes already written.
TEST(PointFormats, PcdBinaryCompressedWithHandWrittenLzf) {
  const float xs[] = {1, 1, 1, 2, 3}, ys[] = {4, 5, 6, 7, 8}, zs[] = {0.5f, 0.5f, 0.5f, 0.5f, 0.5f};
  const uint8_t is[] = {10, 20, 30, 40, 50};
  Bytes expanded;
  for (float v : xs) expanded.put(v);
  for (float v : ys) expanded.put(v);
  for (float v : zs) expanded.put(v);
  for (uint8_t v : is) expanded.put(v);
  ASSERT_EQ(expanded.text.size(), 65u);
  const auto bytes_of = [](float v) { return Bytes().put(v).text; };
  Bytes lzf;
  lzf.put<uint8_t>(3).put_text(bytes_of(1));                   // 4 literal bytes: x0
  lzf.put<uint8_t>(0xC0).put<uint8_t>(3);                      // 8 bytes from 4 back: x1, x2
  lzf.put<uint8_t>(27).put_text(expanded.text.substr(12, 28));  // x3, x4, y0..y4
  lzf.put<uint8_t>(3).put_text(bytes_of(0.5f));                // z0
  lzf.put<uint8_t>(0xE0).put<uint8_t>(7).put<uint8_t>(3);     // 7 + 7 + 2 = 16 bytes from 4 back: z1..z4
  lzf.put<uint8_t>(4).put_text(expanded.text.substr(60, 5));   // the intensities
  const std::vector<char> compressed(lzf.text.begin(), lzf.text.end());
  const std::vector<char> out = lzf_decompress(compressed, 65, "hand.lzf");
  EXPECT_EQ(std::string(out.begin(), out.end()), expanded.text);

  const fs::path dir = test::temp_dir();
  Bytes file;
  file.put_text("FIELDS x y z intensity\nSIZE 4 4 4 1\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 5\nHEIGHT 1\n"
                "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 5\nDATA binary_compressed\n");
  file.put(static_cast<uint32_t>(lzf.text.size())).put(uint32_t{65}).put_text(lzf.text);
  expect_points(read_points(write(dir / "a.pcd", file.text)).points,
                {{1, 4, 0.5f, 10}, {1, 5, 0.5f, 20}, {1, 6, 0.5f, 30}, {2, 7, 0.5f, 40}, {3, 8, 0.5f, 50}});

  // Corrupt streams: a reference before the start, past the declared size, a cut run, too short.
  const auto lzf_error = [](const std::string& stream, size_t size) {
    const std::vector<char> c(stream.begin(), stream.end());
    return error_of([&] { lzf_decompress(c, size, "bad.pcd"); });
  };
  EXPECT_THAT(lzf_error(std::string("\x00" "A" "\x20\x05", 4), 4),
              HasSubstr("bad.pcd: LZF back-reference 6 bytes back at output byte 1, before the start"));
  EXPECT_THAT(lzf_error(std::string("\x01" "AB", 3), 1), HasSubstr("LZF data expands past the declared 1 bytes"));
  EXPECT_THAT(lzf_error(std::string("\x05" "AB", 3), 6), HasSubstr("LZF literal run at byte 0 runs past the end"));
  EXPECT_THAT(lzf_error(std::string("\x01" "AB", 3), 5), HasSubstr("LZF data expands to 2 bytes, not the declared 5"));
  EXPECT_THAT(lzf_error(std::string("\x01" "AB", 3), 1000), HasSubstr("LZF data of 3 bytes cannot expand to 1000"));
}

TEST(PointFormats, PlyAsciiAndBinaryBothEndians) {
  const fs::path dir = test::temp_dir();
  // An element before the vertices (walked past), a list among the vertex properties.
  const std::string ascii =
      "ply\nformat ascii 1.0\ncomment made by hand\nelement camera 1\nproperty float fov\n"
      "property list uchar int ids\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
      "property list uchar float extra\nproperty uchar intensity\nelement face 1\n"
      "property list uchar int vertex_indices\nend_header\n"
      "60 2 7 8\n"
      "1.5 -2.25 0.125 0 128\n-30 12.5 -1.75 2 0.5 0.5 64\n0 0 3 1 9 255\n"
      "3 0 1 2\n";
  expect_points(read_points(write(dir / "a.ply", ascii)).points,
                {{1.5f, -2.25f, 0.125f, 128}, {-30, 12.5f, -1.75f, 64}, {0, 0, 3, 255}});

  for (const bool big : {false, true}) {
    SCOPED_TRACE(big ? "big endian" : "little endian");
    Bytes b;
    b.put_text(std::string("ply\nformat ") + (big ? "binary_big_endian" : "binary_little_endian") +
               " 1.0\nelement vertex 3\nproperty double reflectance\nproperty float x\nproperty float y\n"
               "property float z\nproperty short ring\nend_header\n");
    for (const Point& p : kPoints)
      b.put(static_cast<double>(p.r), big).put(p.x, big).put(p.y, big).put(p.z, big).put<int16_t>(-3, big);
    expect_points(read_points(write(dir / (big ? "be.ply" : "le.ply"), b.text)).points, kPoints);
  }
  // Without an intensity: reflectance 0; int32 coordinates are converted.
  Bytes c;
  c.put_text("ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty int x\nproperty int y\n"
             "property int z\nend_header\n");
  c.put<int32_t>(-4).put<int32_t>(5).put<int32_t>(6);
  expect_points(read_points(write(dir / "c.ply", c.text)).points, {{-4, 5, 6, 0}});
}

TEST(PointFormats, MalformedFilesSayWhatIsWrong) {
  const fs::path dir = test::temp_dir();
  const auto error = [&](const std::string& name, const std::string& bytes,
                         PointFormat format = PointFormat::FromExtension) {
    const fs::path path = write(dir / name, bytes);
    return error_of([&] { read_points(path, format); });
  };
  Bytes kitti;  // 5 KITTI records: 80 bytes, a multiple of 16 and of 20
  for (int i = 0; i < 5; ++i) kitti.put(-30.0f + static_cast<float>(i)).put(1.0f).put(2.0f).put(0.5f);
  // Never guessed from the size: KITTI records named .npy or .pcd.bin are refused.
  EXPECT_THAT(error("kitti.npy", kitti.text), HasSubstr("kitti.npy: not a NumPy .npy file (no \\x93NUMPY magic"));
  EXPECT_THAT(error("kitti.pcd.bin", kitti.text),
              HasSubstr("kitti.pcd.bin: point 0 has -29 as its ring (the 5th float), not a whole number in [0, 1023]"));
  EXPECT_THAT(error("kitti.pcd", kitti.text), HasSubstr("kitti.pcd: PCD header line 1: unknown header entry"));
  EXPECT_THAT(error("kitti.ply", kitti.text), HasSubstr("kitti.ply: not a PLY file"));
  EXPECT_THAT(error("short.pcd.bin", kitti.text.substr(0, 64)), HasSubstr("short.pcd.bin: size 64 bytes is not a multiple of 20"));
  // ... and the other formats named .bin are refused as KITTI records.
  const std::string good_npy = npy("<f4", "(1, 4)", kitti.text.substr(0, 16));
  EXPECT_THAT(error("npy.bin", good_npy + std::string(16 - good_npy.size() % 16, '\0')),
              HasSubstr("npy.bin: starts like a NumPy .npy file, not a KITTI .bin"));
  EXPECT_THAT(error("odd.bin", kitti.text.substr(0, 20)), HasSubstr("odd.bin: size 20 bytes is not a multiple of 16"));

  // NumPy.
  const std::string row = kitti.text.substr(0, 16);
  EXPECT_THAT(error("f.npy", npy("<f4", "(1, 4)", row, 1, "True")), HasSubstr("f.npy: .npy array is in Fortran order"));
  EXPECT_THAT(error("i.npy", npy("<i4", "(1, 4)", row)), HasSubstr("i.npy: .npy dtype '<i4': expected float32 or float64"));
  EXPECT_THAT(error("s.npy", npy("<f4", "(4,)", row)), HasSubstr("s.npy: .npy shape (4): expected (N, 3), (N, 4) or (N, 5)"));
  EXPECT_THAT(error("w.npy", npy("<f4", "(1, 6)", row + row.substr(0, 8))), HasSubstr(".npy shape (1, 6)"));
  EXPECT_THAT(error("t.npy", npy("<f4", "(2, 4)", row)),
              HasSubstr("t.npy: .npy array of shape (2, 4) <f4 needs 32 bytes, the file holds 16 (truncated?)"));
  EXPECT_THAT(error("x.npy", npy("<f4", "(1, 4)", row + "x")), HasSubstr("needs 16 bytes, the file holds 17"));
  EXPECT_THAT(error("v.npy", npy("<f4", "(1, 4)", row, 4)), HasSubstr("v.npy: .npy format version 4.0"));
  EXPECT_THAT(error("h.npy", std::string("\x93NUMPY\x01\x00\xff\x00{", 11)), HasSubstr("h.npy: .npy header of 255 bytes runs past the end"));
  std::string bad_key = npy("<f4", "(1, 4)", row);
  bad_key.replace(bad_key.find("'shape'"), 7, "'shapz'");
  EXPECT_THAT(error("k.npy", bad_key), HasSubstr("k.npy: .npy header at byte"));
  EXPECT_THAT(error("k.npy", bad_key), HasSubstr("unexpected key 'shapz'"));

  // PCD.
  const std::string head = "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n";
  EXPECT_THAT(error("noz.pcd", "FIELDS x y w\nSIZE 4 4 4\nTYPE F F F\nPOINTS 0\nDATA ascii\n"),
              HasSubstr("noz.pcd: PCD header: no field 'z' (x, y and z are required; fields: x y w)"));
  EXPECT_THAT(error("data.pcd", head + "POINTS 0\nDATA binary_lzma\n"),
              HasSubstr("data.pcd: PCD header line 5: DATA 'binary_lzma' (expected ascii, binary or binary_compressed)"));
  EXPECT_THAT(error("nodata.pcd", head + "POINTS 0\n"), HasSubstr("nodata.pcd: PCD header ends without a DATA line"));
  EXPECT_THAT(error("type.pcd", "FIELDS x y z\nSIZE 4 4 2\nTYPE F F F\nPOINTS 0\nDATA ascii\n"),
              HasSubstr("field 'z': TYPE F with SIZE 2 (expected F 4/8, I or U 1/2/4/8)"));
  EXPECT_THAT(error("grid.pcd", head + "WIDTH 3\nHEIGHT 2\nPOINTS 5\nDATA ascii\n"),
              HasSubstr("grid.pcd: PCD header: WIDTH x HEIGHT = 3 x 2 is not POINTS 5"));
  EXPECT_THAT(error("trunc.pcd", head + "POINTS 2\nDATA binary\n" + std::string(20, '\0')),
              HasSubstr("trunc.pcd: binary data of 20 bytes, but 2 points of 12 bytes need 24 (truncated file?)"));
  EXPECT_THAT(error("lines.pcd", head + "POINTS 2\nDATA ascii\n1 2 3\n4 5\n"),
              HasSubstr("lines.pcd: line 7: 2 values, expected 3"));
  EXPECT_THAT(error("few.pcd", head + "POINTS 3\nDATA ascii\n1 2 3\n4 5 6\n"),
              HasSubstr("few.pcd: 2 point lines, but POINTS says 3"));
  EXPECT_THAT(error("word.pcd", head + "POINTS 1\nDATA ascii\n1 two 3\n"), HasSubstr("word.pcd: line 6: y value 'two' is not a number"));
  EXPECT_THAT(error("count.pcd", head + "COUNT 1 2 1\nPOINTS 0\nDATA ascii\n"), HasSubstr("field 'y' has COUNT 2 (expected 1)"));
  EXPECT_THAT(error("twice.pcd", "FIELDS x y z x\nSIZE 4 4 4 4\nTYPE F F F F\nPOINTS 0\nDATA ascii\n"),
              HasSubstr("field 'x' appears twice"));
  Bytes compressed_sizes;
  compressed_sizes.put(uint32_t{4}).put(uint32_t{12}).put_text("\x02" "abc");
  EXPECT_THAT(error("sizes.pcd", head + "POINTS 2\nDATA binary_compressed\n" + compressed_sizes.text),
              HasSubstr("sizes.pcd: binary_compressed data expands to 12 bytes, but 2 points of 12 bytes are 24"));

  // PLY.
  EXPECT_THAT(error("nov.ply", "ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int v\nend_header\n"),
              HasSubstr("nov.ply: PLY file has no 'vertex' element"));
  EXPECT_THAT(error("fmt.ply", "ply\nformat binary 1.0\nend_header\n"),
              HasSubstr("fmt.ply: PLY header line 2: 'format binary 1.0' (expected 'format ascii|binary_little_endian|binary_big_endian 1.0')"));
  const std::string vertex = "element vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
  EXPECT_THAT(error("cut.ply", "ply\nformat binary_big_endian 1.0\n" + vertex + std::string(16, '\0')),
              HasSubstr("cut.ply: the data ends inside vertex 1 property 'y' (truncated file?)"));
  EXPECT_THAT(error("tail.ply", "ply\nformat binary_little_endian 1.0\n" + vertex + std::string(25, '\0')),
              HasSubstr("tail.ply: 1 bytes after the last vertex"));
  EXPECT_THAT(error("type.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n"),
              HasSubstr("type.ply: PLY header line 4: unknown property type 'half'"));
  EXPECT_THAT(error("end.ply", "ply\nformat ascii 1.0\n" + vertex.substr(0, 17)), HasSubstr("end.ply: PLY header ends without 'end_header'"));
  EXPECT_THAT(error("many.ply", "ply\nformat ascii 1.0\nelement vertex 1000\nproperty float x\nproperty float y\n"
                                "property float z\nend_header\n1 2 3\n"),
              HasSubstr("many.ply: 1000 vertices, but only 6 bytes of data are left"));
  EXPECT_THAT(error("nan.ply", "ply\nformat ascii 1.0\n" + vertex + "1 2 3\n4 five 6\n"),
              HasSubstr("nan.ply: vertex 1 property 'y': 'five' is not a number"));
}

// The real scan of kitti_object converted here to .npy, PCD (binary, binary_compressed as literal
// LZF runs, ascii) and binary PLY: every reader gives the KITTI reader's points, bit for bit.
TEST(PointFormats, RealScanConvertedToEveryFormatReadsBackIdentically) {
  const fs::path scan_file = test::shared_data_dir() / "kitti_object" / "004139.bin";
  if (!fs::exists(scan_file)) GTEST_SKIP() << "no " << scan_file.string() << " (the shared data is absent)";
  const Scan kitti = read_points(scan_file);
  ASSERT_GT(kitti.points.size(), 100000u);
  const std::vector<Point>& p = kitti.points;
  const fs::path dir = test::temp_dir();
  const size_t n = p.size();

  Bytes records;
  for (const Point& q : p) records.put(q.x).put(q.y).put(q.z).put(q.r);
  const std::string shape = fmt::format("({}, 4)", n);
  EXPECT_TRUE(same_bits(read_points(write(dir / "scan.npy", npy("<f4", shape, records.text))).points, p));

  const std::string pcd_head = fmt::format(
      "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {}\n"
      "HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {}\n", n, n);
  EXPECT_TRUE(same_bits(read_points(write(dir / "scan.pcd", pcd_head + "DATA binary\n" + records.text)).points, p));

  Bytes by_field;
  for (const Point& q : p) by_field.put(q.x);
  for (const Point& q : p) by_field.put(q.y);
  for (const Point& q : p) by_field.put(q.z);
  for (const Point& q : p) by_field.put(q.r);
  std::string literal_runs;
  for (size_t at = 0; at < by_field.text.size(); at += 32) {
    const size_t run = std::min<size_t>(32, by_field.text.size() - at);
    literal_runs += static_cast<char>(run - 1);
    literal_runs += by_field.text.substr(at, run);
  }
  Bytes compressed;
  compressed.put(static_cast<uint32_t>(literal_runs.size())).put(static_cast<uint32_t>(by_field.text.size()));
  EXPECT_TRUE(same_bits(
      read_points(write(dir / "scan_lzf.pcd", pcd_head + "DATA binary_compressed\n" + compressed.text + literal_runs))
          .points,
      p));

  std::string ascii = pcd_head + "DATA ascii\n";
  for (const Point& q : p) ascii += fmt::format("{} {} {} {}\n", q.x, q.y, q.z, q.r);  // shortest round trip
  EXPECT_TRUE(same_bits(read_points(write(dir / "scan_ascii.pcd", ascii)).points, p));

  Bytes ply;
  ply.put_text(fmt::format("ply\nformat binary_big_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\n"
                           "property float z\nproperty float intensity\nend_header\n", n));
  for (const Point& q : p) ply.put(q.x, true).put(q.y, true).put(q.z, true).put(q.r, true);
  EXPECT_TRUE(same_bits(read_points(write(dir / "scan.ply", ply.text)).points, p));
}

TEST(PointFormats, SequencesFindEveryFormat) {
  const fs::path root = test::temp_dir();
  const fs::path velodyne = root / "sequences" / "03" / "velodyne";
  write_bin(velodyne / "000000.bin", kPoints);
  Bytes n;
  for (const Point& q : kPoints) n.put(q.x).put(q.y).put(q.z).put(q.r).put(0.0f);
  write(velodyne / "000001.pcd.bin", n.text);
  Bytes f;
  for (const Point& q : kPoints) f.put(q.x).put(q.y).put(q.z).put(q.r);
  write(velodyne / "000002.npy", npy("<f4", "(3, 4)", f.text));
  write(velodyne / "notes.txt", "not a scan");
  write_labels(root / "sequences" / "03" / "labels" / "000002.label", {1, 2, 3});
  const Sequence seq(root, 3);
  ASSERT_EQ(seq.size(), 3u);
  EXPECT_EQ(seq.scan_path(1).filename(), "000001.pcd.bin");
  EXPECT_EQ(seq.scan_path(2).filename(), "000002.npy");
  for (size_t i = 0; i < 3; ++i) expect_points(seq.load(i).points, kPoints);
  EXPECT_EQ(seq.load(2).labels, (std::vector<uint32_t>{1, 2, 3}));
  write(velodyne / "000002.ply", "ply\n");
  EXPECT_THAT(error_of([&] { const Sequence again(root, 3); }), HasSubstr("two point files of scan 000002: 000002.npy and 000002.ply"));
}

TEST(InputMapping, TransformAndReflectanceByHand) {
  InputMapping m;
  EXPECT_TRUE(m.is_identity());
  EXPECT_EQ(m.describe(), "identity");
  m.transform = transform_from_angles(1.0, 0, 0, 90);  // x -> y, then 1 m up
  m.reflectance = {ReflectanceMapping::Kind::Scale, 1.0f / 255.0f, 0.0f, true};
  std::vector<Point> points = {{2, 0, 0, 255}, {0, 3, -1, 510}, {0, 0, 0, -7}};
  m.apply(points);
  EXPECT_NEAR(points[0].x, 0, 1e-6);
  EXPECT_NEAR(points[0].y, 2, 1e-6);
  EXPECT_NEAR(points[0].z, 1, 1e-6);
  EXPECT_NEAR(points[1].x, -3, 1e-6);
  EXPECT_NEAR(points[1].y, 0, 1e-6);
  EXPECT_NEAR(points[1].z, 0, 1e-6);
  EXPECT_FLOAT_EQ(points[0].r, 1.0f);
  EXPECT_EQ(points[1].r, 1.0f);  // clipped
  EXPECT_EQ(points[2].r, 0.0f);  // clipped
  m.reflectance.clip = false;
  std::vector<Point> unclipped = {{0, 0, 0, 510}};
  m.apply(unclipped);
  EXPECT_FLOAT_EQ(unclipped[0].r, 2.0f);
  m.reflectance = {ReflectanceMapping::Kind::None, 1, 0, true};
  m.apply(unclipped);
  EXPECT_EQ(unclipped[0].r, 0.0f);
  // Roll, then pitch, then yaw: z up rolled 90 degrees about x points along -y.
  const Pose roll = transform_from_angles(0, 90, 0, 0);
  EXPECT_TRUE((roll.topLeftCorner<3, 3>() * Eigen::Vector3d::UnitZ()).isApprox(-Eigen::Vector3d::UnitY()));
  const Pose pitch = transform_from_angles(0, 0, 90, 0);
  EXPECT_TRUE((pitch.topLeftCorner<3, 3>() * Eigen::Vector3d::UnitX()).isApprox(-Eigen::Vector3d::UnitZ()));
  // Only a mapping that changes the points changes a cache key.
  Hasher a, b;
  InputMapping{}.add_to(a);
  EXPECT_EQ(a.digest(), Hasher().digest());
  InputMapping scaled;
  scaled.reflectance = {ReflectanceMapping::Kind::Scale, 0.5f, 0, true};
  scaled.add_to(b);
  EXPECT_NE(b.digest(), Hasher().digest());
}

TEST(InputMapping, RunConfigSection) {
  const RunConfig plain = parse_run_config("", "plain.yaml");
  EXPECT_TRUE(plain.input.is_identity());
  const RunConfig c = parse_run_config(
      "input:\n  reflectance: {scale: 0.00392157, offset: 0.1, clip: false}\n"
      "  transform: {height: 0.11, yaw: -90}\n",
      "nuscenes.yaml");
  EXPECT_EQ(c.input.reflectance.kind, ReflectanceMapping::Kind::Scale);
  EXPECT_FLOAT_EQ(c.input.reflectance.scale, 0.00392157f);
  EXPECT_FLOAT_EQ(c.input.reflectance.offset, 0.1f);
  EXPECT_FALSE(c.input.reflectance.clip);
  EXPECT_TRUE(c.input.transform.isApprox(transform_from_angles(0.11, 0, 0, -90)));
  EXPECT_NEAR(c.input.transform(0, 1), 1.0, 1e-12);  // the sensor's y (forward) onto x
  const RunConfig rows = parse_run_config(
      "input: {reflectance: none, transform: [[0, -1, 0, 0.5], [1, 0, 0, 0], [0, 0, 1, -0.2], [0, 0, 0, 1]]}\n", "r.yaml");
  EXPECT_EQ(rows.input.reflectance.kind, ReflectanceMapping::Kind::None);
  EXPECT_EQ(rows.input.transform(0, 3), 0.5);
  EXPECT_EQ(rows.input.transform(1, 0), 1.0);
  const RunConfig flat =
      parse_run_config("input: {transform: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 1.5, 0, 0, 0, 1]}\n", "f.yaml");
  EXPECT_EQ(flat.input.transform(2, 3), 1.5);
  EXPECT_EQ(flat.input.reflectance.kind, ReflectanceMapping::Kind::Keep);

  const auto error = [](const std::string& yaml) { return error_of([&] { parse_run_config(yaml, "x.yaml"); }); };
  EXPECT_THAT(error("input: {gain: 2}\n"), HasSubstr("x.yaml: input.gain: unknown key (expected reflectance, transform)"));
  EXPECT_THAT(error("input: {reflectance: {scale: 2, gamma: 1}}\n"),
              HasSubstr("x.yaml: input.reflectance.gamma: unknown key (expected scale, offset, clip)"));
  EXPECT_THAT(error("input: {reflectance: off}\n"), HasSubstr("input.reflectance: 'off': expected none or {scale, offset, clip}"));
  EXPECT_THAT(error("input: {transform: {yaw: east}}\n"), HasSubstr("input.transform.yaw (degrees): expected a number"));
  EXPECT_THAT(error("input: {transform: {heading: 1}}\n"),
              HasSubstr("input.transform.heading: unknown key (expected height in metres, roll, pitch, yaw in degrees)"));
  EXPECT_THAT(error("input: {transform: [1, 0, 0]}\n"), HasSubstr("input.transform: 3 numbers, expected 16"));
  EXPECT_THAT(error("input: {transform: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 1]}\n"),
              HasSubstr("the transform's bottom row is [0 0 1 1], expected [0 0 0 1]"));
  EXPECT_THAT(error("input: {transform: [0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}\n"),
              HasSubstr("the transform's 3 x 3 part is singular"));
  EXPECT_THAT(error("inputs: {}\n"), HasSubstr("unknown section 'inputs' (expected grid, model, train, eval, input)"));
}

// A sequence read through a mapping: its points mapped, and its poses such that scan j's mapped
// points moved into scan i's frame are scan i's frame's mapping of where they were.
TEST(InputMapping, SequencePosesFollowTheMappedPoints) {
  const fs::path root = test::temp_dir();
  const fs::path seq_dir = root / "sequences" / "00";
  write_bin(seq_dir / "velodyne" / "000000.bin", kPoints);
  write_bin(seq_dir / "velodyne" / "000001.bin", kPoints);
  {
    std::ofstream poses(seq_dir / "poses.txt");
    poses << "1 0 0 0 0 1 0 0 0 0 1 0\n0.8 -0.6 0 2 0.6 0.8 0 -1 0 0 1 0.5\n";
    std::ofstream(seq_dir / "calib.txt") << "Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n";
  }
  InputMapping m;
  m.transform = transform_from_angles(1.7, 2, -3, 30);
  m.transform(0, 3) = 0.25;
  const Sequence plain(root, 0), mapped(root, 0, m);
  const Scan original = plain.load(1), moved = mapped.load(1);
  const Pose rel = plain.relative(0, 1), rel_mapped = mapped.relative(0, 1);
  for (size_t k = 0; k < original.points.size(); ++k) {
    const Point& o = original.points[k];
    const Point& q = moved.points[k];
    const Eigen::Vector4d expected = m.transform * rel * Eigen::Vector4d(o.x, o.y, o.z, 1);
    const Eigen::Vector4d got = rel_mapped * Eigen::Vector4d(q.x, q.y, q.z, 1);
    EXPECT_LT((got - expected).norm(), 1e-5) << "point " << k;
    const Eigen::Vector4d direct = m.transform * Eigen::Vector4d(o.x, o.y, o.z, 1);
    EXPECT_NEAR(q.x, direct.x(), 1e-5);
  }
}

// The segmenter maps the points before anything else: segment() of the sensor's points gives
// segment_mapped() of the mapped copy, and not that of the points as given.
TEST(InputMapping, SegmenterAppliesItFirst) {
  const ModelConfig model = test::tiny_config(OccupancyInput::Observability2D);
  ScanSegmenter segmenter(model, make_cpu_backend(), {}, /*seed=*/5);
  std::vector<Point> points = test::random_scan(2000, model.grid, 9);
  for (Point& p : points) p.r *= 255;  // an 8-bit sensor
  InputMapping m;
  m.transform = transform_from_angles(0.3, 0, 0, 180);
  m.reflectance = {ReflectanceMapping::Kind::Scale, 1.0f / 255.0f, 0, true};
  std::vector<Point> mapped = points;
  m.apply(mapped);
  const size_t cells = static_cast<size_t>(model.grid.cells());
  std::vector<uint8_t> direct(cells), through(cells), unmapped(cells);
  std::vector<float> p_direct(12 * cells), p_through(12 * cells);
  segmenter.segment_mapped(mapped, direct.data(), p_direct.data());
  segmenter.segment_mapped(points, unmapped.data());
  segmenter.set_input_mapping(m);
  segmenter.segment(points, through.data(), p_through.data());
  EXPECT_EQ(through, direct);
  EXPECT_EQ(p_through, p_direct);
  EXPECT_NE(p_through, std::vector<float>(12 * cells, p_through[0]));
  std::vector<float> p_unmapped(12 * cells);
  segmenter.segment_mapped(points, unmapped.data(), p_unmapped.data());
  EXPECT_NE(p_unmapped, p_direct);
}

// The run config's input: section reaches every reader of scans: a data set for training and
// evaluation maps its scans, and a checkpoint stores it so that open_segmenter applies it (unless
// another config is named).
TEST(InputMapping, DataSetsAndCheckpointsCarryIt) {
  const std::string tiny =
      "grid: {x: [-6.4, 6.4], y: [-3.2, 3.2], z: [-2.5, 1.5], cell: 0.2, voxel_z: 0.5}\n"
      "model: {max_points_per_pillar: 8, pillar_channels: 4, occupancy: 2d, occupancy_channels: 2, base_width: 4, "
      "depth: 2}\n";
  const RunConfig config =
      parse_run_config(tiny + "input: {reflectance: none, transform: {height: 0.5, yaw: 90}}\n", "mapped.yaml");
  const fs::path root = test::temp_dir();
  write_bin(root / "sequences" / "00" / "velodyne" / "000000.bin", kPoints);
  write_labels(root / "sequences" / "00" / "labels" / "000000.label", {40, 48, 70});
  const ScanDataset data(root, {0}, 1, 0, config.model, ClassTable::defaults(), GroundTruthKind::sparse,
                         root / "cache", false, config.input);
  std::vector<Point> mapped = kPoints;
  config.input.apply(mapped);
  expect_points(data.scan(0).points, mapped);
  EXPECT_EQ(data.scan(0).points[0].r, 0.0f);

  auto backend = make_cpu_backend();
  const PillarSegNet net(config.model, *backend, /*seed=*/3);
  save_checkpoint(root / "mapped.safetensors", net, config, {}, /*with_optimizer=*/false);
  const auto segmenter = open_segmenter(root / "mapped.safetensors", "", SegmenterOptions{});
  EXPECT_EQ(segmenter->input_mapping().reflectance.kind, ReflectanceMapping::Kind::None);
  EXPECT_TRUE(segmenter->input_mapping().transform.isApprox(config.input.transform));
  std::ofstream(root / "plain.yaml") << tiny;
  EXPECT_TRUE(open_segmenter(root / "mapped.safetensors", root / "plain.yaml", SegmenterOptions{})
                  ->input_mapping()
                  .is_identity());
}
