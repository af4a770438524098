// Charts as RGB images (`pillarseg plot`): line charts of series (x, y) with axes, "nice" 1-2-5
// ticks (or decades on a log axis), tick labels, axis titles, a title and a legend; and a heat
// map of a matrix with row and column names and a text in each cell. Text is drawn by FreeType
// from a TrueType font (DejaVu Sans by default, found at run time).
#pragma once

#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "core/classes.hpp"
#include "engine/util/image.hpp"

// FreeType's handles (FT_Library, FT_Face), declared so that FreeType's headers stay in plot.cpp.
struct FT_LibraryRec_;
struct FT_FaceRec_;

namespace pillarseg {

// The font's file: $PILLARSEG_FONT if set, else `fallback` (DejaVu Sans from Debian's
// fonts-dejavu-core). Throws, naming the file (and the package), if it is not there.
inline const std::filesystem::path kDejaVuSans = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf";
std::filesystem::path find_font(const std::filesystem::path& fallback = kDejaVuSans);

// A TrueType font opened with FreeType; draws UTF-8 text in grey-level anti-aliasing. Owns its
// FreeType library and face (the face freed first by the destructor); move-only. One thread at a
// time: every call sets the face's size.
class Font {
 public:
  explicit Font(const std::filesystem::path& file);
  ~Font();
  Font(Font&&) noexcept;
  Font& operator=(Font&&) noexcept;
  Font(const Font&) = delete;
  Font& operator=(const Font&) = delete;

  // Width of the text's advance at `pixels` em size.
  int text_width(std::string_view text, int pixels) const;
  // Pixels above and below the baseline of the font's tallest and deepest glyphs.
  int ascender(int pixels) const;
  int descender(int pixels) const;
  // Draws the text with its baseline starting at (x, y), blended over the image (clipped). With
  // `vertical` it reads bottom to top, the baseline running up from (x, y) (a y-axis title).
  void draw(ImageRgb& image, int x, int y, std::string_view text, int pixels, Rgb colour,
            bool vertical = false) const;

 private:
  struct LibraryDeleter {
    void operator()(FT_LibraryRec_* library) const;
  };
  struct FaceDeleter {
    void operator()(FT_FaceRec_* face) const;
  };
  void set_size(int pixels) const;

  std::filesystem::path file_;
  std::unique_ptr<FT_LibraryRec_, LibraryDeleter> library_;  // declared first: freed last
  std::unique_ptr<FT_FaceRec_, FaceDeleter> face_;
};

// Ticks of an axis over [lo, hi]: the multiples of `step` inside it, where step is the smallest
// of 1, 2, 5 times a power of ten that gives at most max_ticks of them. lo < hi.
struct Ticks {
  double step = 0;
  std::vector<double> values;
};
Ticks nice_ticks(double lo, double hi, int max_ticks = 10);
// On a log axis over [lo, hi] (0 < lo < hi): 1, 2, 5 times the powers of ten inside it when that
// gives at most max_ticks, else the powers of ten alone (every k-th decade where even those are
// too many).
Ticks log_ticks(double lo, double hi, int max_ticks = 10);
// A tick value written with as many decimals as the step needs ("0.3", "20", "0.0005", "2e-06").
std::string tick_label(double value, double step);

// The series of a line chart, drawn in order (later ones on top). NaN y values leave a gap.
struct Series {
  std::string name{};
  std::vector<double> x{}, y{};
  Rgb colour{};
  float line_width = 2.0f;  // pixels; 0: no line
  int marker_radius = 0;    // pixels; 0: no markers
};

struct Chart {
  std::string title{}, x_label{}, y_label{};
  std::vector<Series> series{};
  bool log_y = false;  // every finite y must then be > 0
  // The y range; by default the data's, widened to whole ticks. With y_from_zero it starts at 0.
  std::optional<std::pair<double, double>> y_range{};
  bool y_from_zero = false;
  bool integer_x = false;  // x ticks on whole numbers only (steps, epochs)
  int width = 960, height = 540;
};

// White background, the plot area framed with light grid lines at the ticks (the data kept 3%
// inside the frame where a series has markers); a legend at the right of the plot area when there
// are two or more series. Needs one finite point at least.
ImageRgb render_chart(const Chart& chart, const Font& font);

struct HeatMap {
  std::string title, x_label, y_label;  // x: columns, y: rows
  std::vector<std::string> row_names, column_names;
  // shade[r][c] in [0, 1] (white to dark blue) or NaN (grey: no value); text[r][c] up to two
  // lines ("\n"), written in the cell, in white on the dark cells.
  std::vector<std::vector<double>> shade;
  std::vector<std::vector<std::string>> text;
  int cell = 64;  // pixels a cell
};

ImageRgb render_heat_map(const HeatMap& map, const Font& font);

}  // namespace pillarseg
