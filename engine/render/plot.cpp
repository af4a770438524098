#include "engine/render/plot.hpp"

#include <ft2build.h>
#include FT_FREETYPE_H

#include <algorithm>
#include <cmath>
#include <cstdlib>

#include "core/error.hpp"

namespace pillarseg {

// ---- fonts ----

std::filesystem::path find_font(const std::filesystem::path& fallback) {
  if (const char* env = std::getenv("PILLARSEG_FONT"); env != nullptr && *env != '\0') {
    PS_CHECK(std::filesystem::is_regular_file(env), "PILLARSEG_FONT={}: no such font file", env);
    return env;
  }
  PS_CHECK(std::filesystem::is_regular_file(fallback),
           "{}: no such font file; install the Debian package fonts-dejavu-core "
           "(scripts/install-deps.sh), or set PILLARSEG_FONT to a TrueType font",
           fallback.string());
  return fallback;
}

void Font::LibraryDeleter::operator()(FT_LibraryRec_* library) const {
  FT_Done_FreeType(library);
}
void Font::FaceDeleter::operator()(FT_FaceRec_* face) const {
  FT_Done_Face(face);
}

Font::Font(const std::filesystem::path& file) : file_(file) {
  FT_Library library = nullptr;
  const FT_Error init = FT_Init_FreeType(&library);
  PS_CHECK(init == 0, "FreeType: FT_Init_FreeType failed (error {})", init);
  library_.reset(library);
  FT_Face face = nullptr;
  const FT_Error open = FT_New_Face(library, file.c_str(), 0, &face);
  PS_CHECK(open == 0,
           "{}: FreeType cannot open this font (error {}); set PILLARSEG_FONT to a TrueType font",
           file.string(), open);
  face_.reset(face);
  PS_CHECK(FT_IS_SCALABLE(face), "{}: not a scalable (TrueType or OpenType) font", file.string());
}

Font::~Font() = default;
Font::Font(Font&&) noexcept = default;
Font& Font::operator=(Font&&) noexcept = default;

void Font::set_size(int pixels) const {
  const FT_Error e = FT_Set_Pixel_Sizes(face_.get(), 0, static_cast<FT_UInt>(pixels));
  PS_CHECK(e == 0, "{}: cannot size the font to {} pixels (error {})", file_.string(), pixels, e);
}

int Font::ascender(int pixels) const {
  set_size(pixels);
  return static_cast<int>((face_->size->metrics.ascender + 63) / 64);
}

int Font::descender(int pixels) const {
  set_size(pixels);
  return static_cast<int>((-face_->size->metrics.descender + 63) / 64);
}

namespace {

// The code points of UTF-8 text; a byte that starts no valid sequence stands for itself.
std::vector<char32_t> code_points(std::string_view text) {
  std::vector<char32_t> out;
  for (size_t i = 0; i < text.size();) {
    const auto b = static_cast<unsigned char>(text[i]);
    const size_t extra = b >= 0xF0 ? 3 : b >= 0xE0 ? 2 : b >= 0xC0 ? 1 : 0;
    bool valid = extra > 0 && i + extra < text.size();
    for (size_t k = 1; valid && k <= extra; ++k)
      valid = (static_cast<unsigned char>(text[i + k]) & 0xC0) == 0x80;
    if (!valid) {
      out.push_back(b);
      ++i;
      continue;
    }
    char32_t cp = b & (0x3F >> extra);
    for (size_t k = 1; k <= extra; ++k)
      cp = (cp << 6) | (static_cast<unsigned char>(text[i + k]) & 0x3F);
    out.push_back(cp);
    i += extra + 1;
  }
  return out;
}

// A line of text rasterised into coverage (0..255): column 0 lies `left` pixels right of the
// pen's start, row `ascent` is the baseline.
struct TextMask {
  int width = 0, height = 0, left = 0, ascent = 0;
  std::vector<uint8_t> coverage;
};

// Lays the glyphs out along the baseline in 26.6 fixed point (with the font's kerning), calling
// glyph(pen_x_pixels, slot) for each; returns the advance in 26.6.
template <class F>
FT_Pos lay_out(FT_Face face, std::string_view text, FT_Int32 load_flags, F&& glyph) {
  FT_Pos pen = 0;
  FT_UInt previous = 0;
  for (const char32_t cp : code_points(text)) {
    const FT_UInt index = FT_Get_Char_Index(face, cp);
    if (previous != 0 && index != 0 && FT_HAS_KERNING(face)) {
      FT_Vector kern{};
      if (FT_Get_Kerning(face, previous, index, FT_KERNING_DEFAULT, &kern) == 0) pen += kern.x;
    }
    if (FT_Load_Glyph(face, index, load_flags) != 0) continue;  // a missing glyph: skipped
    glyph(static_cast<int>((pen + 32) >> 6), face->glyph);
    pen += face->glyph->advance.x;
    previous = index;
  }
  return pen;
}

TextMask rasterise(FT_Face face, std::string_view text) {
  struct Placed {
    int x, y, w, h;  // top-left relative to the pen's start on the baseline
    std::vector<uint8_t> pixels;
  };
  std::vector<Placed> glyphs;
  lay_out(face, text, FT_LOAD_RENDER, [&](int pen_x, FT_GlyphSlot slot) {
    const FT_Bitmap& bm = slot->bitmap;
    if (bm.width == 0 || bm.rows == 0 || bm.pixel_mode != FT_PIXEL_MODE_GRAY) return;
    Placed g{pen_x + slot->bitmap_left,
             -slot->bitmap_top,
             static_cast<int>(bm.width),
             static_cast<int>(bm.rows),
             {}};
    g.pixels.resize(static_cast<size_t>(g.w) * g.h);
    for (int r = 0; r < g.h; ++r)
      std::copy_n(bm.buffer + static_cast<ptrdiff_t>(r) * bm.pitch, g.w,
                  g.pixels.data() + static_cast<size_t>(r) * g.w);
    glyphs.push_back(std::move(g));
  });
  TextMask mask;
  if (glyphs.empty()) return mask;
  int x0 = glyphs[0].x, y0 = glyphs[0].y, x1 = x0, y1 = y0;
  for (const Placed& g : glyphs) {
    x0 = std::min(x0, g.x), y0 = std::min(y0, g.y);
    x1 = std::max(x1, g.x + g.w), y1 = std::max(y1, g.y + g.h);
  }
  mask.width = x1 - x0, mask.height = y1 - y0, mask.left = x0, mask.ascent = -y0;
  mask.coverage.assign(static_cast<size_t>(mask.width) * mask.height, 0);
  for (const Placed& g : glyphs) {
    for (int r = 0; r < g.h; ++r) {
      for (int c = 0; c < g.w; ++c) {
        uint8_t& out =
            mask.coverage[static_cast<size_t>(g.y - y0 + r) * mask.width + (g.x - x0 + c)];
        out = std::max(out, g.pixels[static_cast<size_t>(r) * g.w + c]);
      }
    }
  }
  return mask;
}

// Blends `colour` over the pixel with coverage a in [0, 1]; outside the image: nothing.
void blend(ImageRgb& image, int x, int y, Rgb colour, double a) {
  if (x < 0 || y < 0 || x >= image.width || y >= image.height || a <= 0) return;
  a = std::min(a, 1.0);
  uint8_t* p = image.at(x, y);
  const uint8_t c[3] = {colour.r, colour.g, colour.b};
  for (int k = 0; k < 3; ++k) p[k] = static_cast<uint8_t>(std::lround(p[k] + (c[k] - p[k]) * a));
}

}  // namespace

int Font::text_width(std::string_view text, int pixels) const {
  set_size(pixels);
  const FT_Pos advance = lay_out(face_.get(), text, FT_LOAD_DEFAULT, [](int, FT_GlyphSlot) {});
  return static_cast<int>((advance + 32) >> 6);
}

void Font::draw(ImageRgb& image, int x, int y, std::string_view text, int pixels, Rgb colour,
                bool vertical) const {
  set_size(pixels);
  const TextMask mask = rasterise(face_.get(), text);
  for (int r = 0; r < mask.height; ++r) {
    for (int c = 0; c < mask.width; ++c) {
      const uint8_t a = mask.coverage[static_cast<size_t>(r) * mask.width + c];
      if (a == 0) continue;
      const int along = mask.left + c, below = r - mask.ascent;  // along the baseline, below it
      if (vertical)
        blend(image, x + below, y - along, colour, a / 255.0);
      else
        blend(image, x + along, y + below, colour, a / 255.0);
    }
  }
}

// ---- ticks ----

namespace {

constexpr double kTickTolerance = 1e-9;  // of a step: values this close to a multiple are on it

// The k of the multiples k * step inside [lo, hi].
std::pair<int64_t, int64_t> multiples_inside(double lo, double hi, double step) {
  return {static_cast<int64_t>(std::ceil(lo / step - kTickTolerance)),
          static_cast<int64_t>(std::floor(hi / step + kTickTolerance))};
}

}  // namespace

Ticks nice_ticks(double lo, double hi, int max_ticks) {
  PS_CHECK(std::isfinite(lo) && std::isfinite(hi) && lo < hi,
           "nice_ticks: need finite lo < hi, got [{}, {}]", lo, hi);
  PS_CHECK(max_ticks >= 2, "nice_ticks: max_ticks must be >= 2, got {}", max_ticks);
  // Start a decade below the step that would give max_ticks and go up 1, 2, 5, 10, 20, ...
  double decade = std::pow(10.0, std::floor(std::log10((hi - lo) / max_ticks)) - 1);
  for (;; decade *= 10) {
    for (const double m : {1.0, 2.0, 5.0}) {
      const double step = m * decade;
      const auto [first, last] = multiples_inside(lo, hi, step);
      if (last - first + 1 > max_ticks) continue;
      Ticks t;
      t.step = step;
      for (int64_t k = first; k <= last; ++k) t.values.push_back(static_cast<double>(k) * step);
      return t;
    }
  }
}

Ticks log_ticks(double lo, double hi, int max_ticks) {
  PS_CHECK(std::isfinite(lo) && std::isfinite(hi) && 0 < lo && lo < hi,
           "log_ticks: need finite 0 < lo < hi, got [{}, {}]", lo, hi);
  PS_CHECK(max_ticks >= 2, "log_ticks: max_ticks must be >= 2, got {}", max_ticks);
  const int e0 = static_cast<int>(std::floor(std::log10(lo))),
            e1 = static_cast<int>(std::ceil(std::log10(hi)));
  const auto inside = [&](double v) {
    return v >= lo * (1 - kTickTolerance) && v <= hi * (1 + kTickTolerance);
  };
  Ticks t;
  for (int e = e0; e <= e1; ++e) {
    for (const double m : {1.0, 2.0, 5.0}) {
      const double v = m * std::pow(10.0, e);
      if (inside(v)) t.values.push_back(v);
    }
  }
  if (static_cast<int>(t.values.size()) <= max_ticks) return t;
  for (int every = 1;; ++every) {
    t.values.clear();
    for (int e = e0; e <= e1; ++e) {
      const double v = std::pow(10.0, e);
      if (inside(v) && (e - e0) % every == 0) t.values.push_back(v);
    }
    if (static_cast<int>(t.values.size()) <= max_ticks) return t;
  }
}

std::string tick_label(double value, double step) {
  PS_CHECK(step > 0 && std::isfinite(step), "tick_label: step must be finite and > 0, got {}",
           step);
  if (std::abs(value) < step * kTickTolerance) return "0";
  const int decimals = std::max(0, static_cast<int>(std::ceil(-std::log10(step) - kTickTolerance)));
  if (decimals <= 4 && std::abs(value) < 1e6) return fmt::format("{:.{}f}", value, decimals);
  // Scientific: as many mantissa digits as the step's place below the value's leading digit.
  const int digits =
      std::max(0, static_cast<int>(std::floor(std::log10(std::abs(value)) + kTickTolerance) -
                                   std::floor(std::log10(step) + kTickTolerance)));
  std::string s = fmt::format("{:.{}e}", value, digits);  // 2.5e-04
  const size_t e = s.find('e');
  size_t z = e + 2;
  while (z + 1 < s.size() && s[z] == '0') ++z;  // 2.5e-4
  return s.substr(0, e + 2) + s.substr(z);
}

// ---- charts ----

namespace {

const Rgb kBlack{0, 0, 0}, kText{30, 30, 30}, kFrame{90, 90, 90}, kGrid{228, 228, 228},
    kWhite{255, 255, 255};
constexpr int kTitlePx = 17, kLabelPx = 14, kTickPx = 12, kLegendPx = 13;

ImageRgb white_image(int width, int height) {
  ImageRgb image(width, height);
  std::fill(image.pixels.begin(), image.pixels.end(), uint8_t{255});
  return image;
}

void fill_rect(ImageRgb& image, int x0, int y0, int x1, int y1,
               Rgb colour) {  // [x0, x1) x [y0, y1)
  for (int y = std::max(0, y0); y < std::min(image.height, y1); ++y)
    for (int x = std::max(0, x0); x < std::min(image.width, x1); ++x)
      blend(image, x, y, colour, 1.0);
}

void frame_rect(ImageRgb& image, int x0, int y0, int x1, int y1, Rgb colour) {  // inclusive corners
  fill_rect(image, x0, y0, x1 + 1, y0 + 1, colour);
  fill_rect(image, x0, y1, x1 + 1, y1 + 1, colour);
  fill_rect(image, x0, y0, x0 + 1, y1 + 1, colour);
  fill_rect(image, x1, y0, x1 + 1, y1 + 1, colour);
}

// Text centred on x (horizontal) with its baseline at y.
void draw_centred(const Font& font, ImageRgb& image, int x, int y, std::string_view text, int px,
                  Rgb colour) {
  font.draw(image, x - font.text_width(text, px) / 2, y, text, px, colour);
}

// Vertical text reading upwards, centred on (x, y): the y-axis title and column names' centre.
void draw_vertical_centred(const Font& font, ImageRgb& image, int x, int y, std::string_view text,
                           int px, Rgb colour) {
  const int baseline_x = x + (font.ascender(px) - font.descender(px)) / 2;
  font.draw(image, baseline_x, y + font.text_width(text, px) / 2, text, px, colour,
            /*vertical=*/true);
}

// Anti-aliased coverage of strokes and discs inside a clip rectangle, kept as the maximum over
// everything drawn (so joints of a polyline are not blended twice), then blended once.
class CoverageMask {
 public:
  CoverageMask(int x0, int y0, int x1, int y1)  // clip [x0, x1] x [y0, y1], inclusive
      : x0_(x0),
        y0_(y0),
        w_(x1 - x0 + 1),
        h_(y1 - y0 + 1),
        cover_(static_cast<size_t>(w_) * h_, 0.0f) {}

  // A segment of the given width with round caps.
  void segment(double ax, double ay, double bx, double by, double width) {
    const double r = width / 2;
    const double dx = bx - ax, dy = by - ay, len2 = dx * dx + dy * dy;
    stamp(std::min(ax, bx) - r - 1, std::min(ay, by) - r - 1, std::max(ax, bx) + r + 1,
          std::max(ay, by) + r + 1, [&](double px, double py) {
            const double t =
                len2 > 0 ? std::clamp(((px - ax) * dx + (py - ay) * dy) / len2, 0.0, 1.0) : 0.0;
            return r + 0.5 - std::hypot(px - (ax + t * dx), py - (ay + t * dy));
          });
  }
  void disc(double cx, double cy, double r) {
    stamp(cx - r - 1, cy - r - 1, cx + r + 1, cy + r + 1,
          [&](double px, double py) { return r + 0.5 - std::hypot(px - cx, py - cy); });
  }
  void blend_into(ImageRgb& image, Rgb colour) const {
    for (int y = 0; y < h_; ++y)
      for (int x = 0; x < w_; ++x)
        blend(image, x0_ + x, y0_ + y, colour, cover_[static_cast<size_t>(y) * w_ + x]);
  }

 private:
  // Coverage clamp(f(x, y), 0, 1) at the pixel centres of the box, within the clip.
  template <class F>
  void stamp(double bx0, double by0, double bx1, double by1, F&& f) {
    const int ix0 = std::max(0, static_cast<int>(std::floor(bx0)) - x0_);
    const int iy0 = std::max(0, static_cast<int>(std::floor(by0)) - y0_);
    const int ix1 = std::min(w_ - 1, static_cast<int>(std::ceil(bx1)) - x0_);
    const int iy1 = std::min(h_ - 1, static_cast<int>(std::ceil(by1)) - y0_);
    for (int y = iy0; y <= iy1; ++y) {
      for (int x = ix0; x <= ix1; ++x) {
        const float c = static_cast<float>(std::clamp(f(x0_ + x, y0_ + y), 0.0, 1.0));
        float& out = cover_[static_cast<size_t>(y) * w_ + x];
        out = std::max(out, c);
      }
    }
  }

  int x0_, y0_, w_, h_;
  std::vector<float> cover_;
};

// An axis: the data range it shows, its ticks and the mapping to pixels [p0, p1].
struct Axis {
  double lo = 0, hi = 1;
  bool log = false;
  Ticks ticks;
  double pixel(double v, double p0, double p1) const {
    const double t = log ? (std::log10(v) - std::log10(lo)) / (std::log10(hi) - std::log10(lo))
                         : (v - lo) / (hi - lo);
    return p0 + t * (p1 - p0);
  }
  std::string label(double v) const { return tick_label(v, log ? v : ticks.step); }
};

bool usable(double x, double y, bool log_y) {
  return std::isfinite(x) && std::isfinite(y) && (!log_y || y > 0);
}

// The 1, 2, 5 times a power of ten at or below (or above) v > 0.
double floor_125(double v) {
  const double decade = std::pow(10.0, std::floor(std::log10(v)));
  for (const double m : {5.0, 2.0, 1.0})
    if (m * decade <= v * (1 + kTickTolerance)) return m * decade;
  return decade;
}
double ceil_125(double v) {
  const double decade = std::pow(10.0, std::floor(std::log10(v)));
  for (const double m : {1.0, 2.0, 5.0, 10.0})
    if (m * decade >= v * (1 - kTickTolerance)) return m * decade;
  return 10 * decade;
}

Axis x_axis(const Chart& chart, double lo, double hi) {
  Axis a;
  if (lo == hi) lo -= 1, hi += 1;
  a.lo = lo, a.hi = hi;
  a.ticks = nice_ticks(lo, hi, 10);
  if (chart.integer_x && a.ticks.step < 1) {
    a.ticks = Ticks{1.0, {}};
    const auto [first, last] = multiples_inside(lo, hi, 1.0);
    for (int64_t k = first; k <= last; ++k) a.ticks.values.push_back(static_cast<double>(k));
  }
  return a;
}

Axis y_axis(const Chart& chart, double lo, double hi) {
  Axis a;
  if (chart.y_range) {
    a.lo = chart.y_range->first, a.hi = chart.y_range->second;
    PS_CHECK(a.lo < a.hi && (!chart.log_y || a.lo > 0), "chart '{}': bad y range [{}, {}]",
             chart.title, a.lo, a.hi);
  } else if (chart.log_y) {
    a.lo = floor_125(lo), a.hi = ceil_125(hi);
    if (a.lo == a.hi) a.lo /= 2, a.hi *= 2;
  } else {
    if (chart.y_from_zero) lo = std::min(lo, 0.0);
    if (lo == hi) {
      const double half = lo == 0 ? 1.0 : std::abs(lo) * 0.1;
      lo = chart.y_from_zero && lo >= 0 ? 0.0 : lo - half, hi += half;
    }
    const Ticks inner = nice_ticks(lo, hi, 8);  // widened to whole steps below: at most 10 ticks
    a.lo = std::floor(lo / inner.step + kTickTolerance) * inner.step;
    a.hi = std::ceil(hi / inner.step - kTickTolerance) * inner.step;
  }
  a.log = chart.log_y;
  a.ticks = a.log ? log_ticks(a.lo, a.hi, 10) : nice_ticks(a.lo, a.hi, 10);
  return a;
}

}  // namespace

ImageRgb render_chart(const Chart& chart, const Font& font) {
  PS_CHECK(chart.width >= 200 && chart.height >= 150,
           "chart '{}': {}x{} is too small (at least 200x150)", chart.title, chart.width,
           chart.height);
  double x_lo = INFINITY, x_hi = -INFINITY, y_lo = INFINITY, y_hi = -INFINITY;
  for (const Series& s : chart.series) {
    PS_CHECK(s.x.size() == s.y.size(), "chart '{}': series '{}' has {} x and {} y values",
             chart.title, s.name, s.x.size(), s.y.size());
    for (size_t i = 0; i < s.x.size(); ++i) {
      if (!usable(s.x[i], s.y[i], chart.log_y)) continue;
      x_lo = std::min(x_lo, s.x[i]), x_hi = std::max(x_hi, s.x[i]);
      y_lo = std::min(y_lo, s.y[i]), y_hi = std::max(y_hi, s.y[i]);
    }
  }
  PS_CHECK(x_lo <= x_hi, "chart '{}': no finite point to draw{}", chart.title,
           chart.log_y ? " (log axis: y > 0)" : "");
  const Axis xa = x_axis(chart, x_lo, x_hi), ya = y_axis(chart, y_lo, y_hi);

  // Layout: title on top; y tick labels and the y title on the left; x tick labels and the x title
  // below; the legend, if any, on the right.
  const int tick_len = 5, pad = 14;
  const int tick_h = font.ascender(kTickPx) + font.descender(kTickPx);
  const int label_h = font.ascender(kLabelPx) + font.descender(kLabelPx);
  int y_label_w = 0;
  for (const double v : ya.ticks.values)
    y_label_w = std::max(y_label_w, font.text_width(ya.label(v), kTickPx));
  const bool legend = chart.series.size() >= 2;
  const int swatch = 28, legend_row = kLegendPx + 9;
  int legend_w = 0;
  if (legend) {
    for (const Series& s : chart.series)
      legend_w = std::max(legend_w, font.text_width(s.name, kLegendPx));
    legend_w += 10 + swatch + 8 + 10;
  }
  const int left = pad + label_h + 10 + y_label_w + 6 + tick_len;
  const int top = pad + font.ascender(kTitlePx) + font.descender(kTitlePx) + 14;
  const int bottom = tick_len + 5 + tick_h + 10 + label_h + pad;
  const int right = legend ? legend_w + 2 * pad : 2 * pad;
  const int px0 = left, py0 = top, px1 = chart.width - right,
            py1 = chart.height - bottom;  // inclusive
  PS_CHECK(px1 - px0 >= 50 && py1 - py0 >= 50, "chart '{}': {}x{} leaves no room for the plot area",
           chart.title, chart.width, chart.height);

  ImageRgb image = white_image(chart.width, chart.height);
  // With markers the data keeps 3% of the plot area (and a marker) clear of the frame, so that the
  // markers at the ends show whole.
  int marker = 0;
  for (const Series& s : chart.series) marker = std::max(marker, s.marker_radius);
  const int inset_x = marker > 0 ? std::max(marker + 3, (px1 - px0) * 3 / 100) : 0;
  const int inset_y = marker > 0 ? std::max(marker + 3, (py1 - py0) * 3 / 100) : 0;
  const auto x_px = [&](double v) { return xa.pixel(v, px0 + inset_x, px1 - inset_x); };
  const auto y_px = [&](double v) { return ya.pixel(v, py1 - inset_y, py0 + inset_y); };

  // Grid lines and ticks with their labels.
  for (const double v : xa.ticks.values) {
    const int x = static_cast<int>(std::lround(x_px(v)));
    fill_rect(image, x, py0 + 1, x + 1, py1, kGrid);
    fill_rect(image, x, py1 + 1, x + 1, py1 + 1 + tick_len, kFrame);
    draw_centred(font, image, x, py1 + tick_len + 4 + font.ascender(kTickPx), xa.label(v), kTickPx,
                 kText);
  }
  for (const double v : ya.ticks.values) {
    const int y = static_cast<int>(std::lround(y_px(v)));
    fill_rect(image, px0 + 1, y, px1, y + 1, kGrid);
    fill_rect(image, px0 - tick_len, y, px0, y + 1, kFrame);
    const std::string text = ya.label(v);
    font.draw(image, px0 - tick_len - 4 - font.text_width(text, kTickPx),
              y + (font.ascender(kTickPx) - 2) / 2, text, kTickPx, kText);
  }

  // The series, clipped to the plot area.
  for (const Series& s : chart.series) {
    CoverageMask mask(px0 + 1, py0 + 1, px1 - 1, py1 - 1);
    size_t run_start = 0;
    for (size_t i = 0; i <= s.x.size(); ++i) {
      const bool ok = i < s.x.size() && usable(s.x[i], s.y[i], chart.log_y);
      if (ok && i > run_start && s.line_width > 0)
        mask.segment(x_px(s.x[i - 1]), y_px(s.y[i - 1]), x_px(s.x[i]), y_px(s.y[i]), s.line_width);
      if (ok && s.marker_radius > 0) mask.disc(x_px(s.x[i]), y_px(s.y[i]), s.marker_radius);
      if (!ok) {
        // A point alone between gaps: a dot, so that it shows without markers.
        if (i == run_start + 1 && s.marker_radius == 0)
          mask.disc(x_px(s.x[run_start]), y_px(s.y[run_start]), std::max(1.5, s.line_width / 2.0));
        run_start = i + 1;
      }
    }
    mask.blend_into(image, s.colour);
  }
  frame_rect(image, px0, py0, px1, py1, kFrame);

  // Titles.
  draw_centred(font, image, (px0 + px1) / 2, pad + font.ascender(kTitlePx), chart.title, kTitlePx,
               kBlack);
  draw_centred(font, image, (px0 + px1) / 2, chart.height - pad - font.descender(kLabelPx),
               chart.x_label, kLabelPx, kText);
  draw_vertical_centred(font, image, pad + label_h / 2, (py0 + py1) / 2, chart.y_label, kLabelPx,
                        kText);

  // Legend: a swatch of each series' line (and marker) and its name, in a framed box.
  if (legend) {
    const int lx0 = px1 + pad, ly0 = py0, lx1 = lx0 + legend_w;
    const int ly1 = ly0 + 8 + legend_row * static_cast<int>(chart.series.size()) + 4;
    frame_rect(image, lx0, ly0, lx1, ly1, kGrid);
    int y = ly0 + 8;
    for (const Series& s : chart.series) {
      const int mid = y + legend_row / 2 - 1;
      CoverageMask mask(lx0 + 1, ly0 + 1, lx1 - 1, ly1 - 1);
      if (s.line_width > 0)
        mask.segment(lx0 + 10, mid, lx0 + 10 + swatch, mid, std::max(2.0f, s.line_width));
      if (s.marker_radius > 0) mask.disc(lx0 + 10 + swatch / 2.0, mid, s.marker_radius);
      mask.blend_into(image, s.colour);
      font.draw(image, lx0 + 10 + swatch + 8, mid + (font.ascender(kLegendPx) - 2) / 2, s.name,
                kLegendPx, kText);
      y += legend_row;
    }
  }
  return image;
}

// ---- heat map ----

namespace {

// White to dark blue through a middle blue (the "Blues" ramp), t in [0, 1].
Rgb blues(double t) {
  const Rgb stops[3] = {{247, 251, 255}, {107, 174, 214}, {8, 48, 107}};
  t = std::clamp(t, 0.0, 1.0) * 2;
  const int k = std::min(1, static_cast<int>(t));
  const double f = t - k;
  const auto mix = [&](uint8_t a, uint8_t b) {
    return static_cast<uint8_t>(std::lround(a + (b - a) * f));
  };
  return {mix(stops[k].r, stops[k + 1].r), mix(stops[k].g, stops[k + 1].g),
          mix(stops[k].b, stops[k + 1].b)};
}

}  // namespace

ImageRgb render_heat_map(const HeatMap& map, const Font& font) {
  const int n = static_cast<int>(map.row_names.size()),
            m = static_cast<int>(map.column_names.size());
  PS_CHECK(n > 0 && m > 0, "heat map '{}': no rows or no columns", map.title);
  PS_CHECK(map.shade.size() == static_cast<size_t>(n) && map.text.size() == static_cast<size_t>(n),
           "heat map '{}': {} rows named, {} shade rows, {} text rows", map.title, n,
           map.shade.size(), map.text.size());
  for (int r = 0; r < n; ++r)
    PS_CHECK(map.shade[r].size() == static_cast<size_t>(m) &&
                 map.text[r].size() == static_cast<size_t>(m),
             "heat map '{}': row {} has {} shades and {} texts, expected {}", map.title, r,
             map.shade[r].size(), map.text[r].size(), m);
  PS_CHECK(map.cell >= 8, "heat map '{}': cells of {} pixels are too small", map.title, map.cell);

  const int pad = 14, name_px = kTickPx + 1, main_px = 13, second_px = 10;
  const int label_h = font.ascender(kLabelPx) + font.descender(kLabelPx);
  int row_w = 0, column_w = 0;
  for (const std::string& s : map.row_names) row_w = std::max(row_w, font.text_width(s, name_px));
  for (const std::string& s : map.column_names)
    column_w = std::max(column_w, font.text_width(s, name_px));
  const int gx0 = pad + label_h + 10 + row_w + 8;
  const int gy0 = pad + font.ascender(kTitlePx) + font.descender(kTitlePx) + 14;
  const int gx1 = gx0 + m * map.cell, gy1 = gy0 + n * map.cell;  // exclusive
  const int title_w = font.text_width(map.title, kTitlePx);
  const int width = std::max(gx1 + 2 * pad, title_w + 2 * pad);
  const int height = gy1 + 8 + column_w + 10 + label_h + pad;
  ImageRgb image = white_image(width, height);

  for (int r = 0; r < n; ++r) {
    for (int c = 0; c < m; ++c) {
      const double v = map.shade[r][c];
      const int x = gx0 + c * map.cell, y = gy0 + r * map.cell;
      fill_rect(image, x, y, x + map.cell, y + map.cell,
                std::isnan(v) ? Rgb{235, 235, 235} : blues(v));
      const Rgb ink = !std::isnan(v) && v > 0.55 ? kWhite : kText;
      const std::string& text = map.text[r][c];
      const size_t newline = text.find('\n');
      const int cx = x + map.cell / 2, cy = y + map.cell / 2;
      if (newline == std::string::npos) {
        draw_centred(font, image, cx, cy + (font.ascender(main_px) - 2) / 2, text, main_px, ink);
      } else {
        draw_centred(font, image, cx, cy - 2, std::string_view(text).substr(0, newline), main_px,
                     ink);
        draw_centred(font, image, cx, cy + 2 + font.ascender(second_px),
                     std::string_view(text).substr(newline + 1), second_px, ink);
      }
    }
  }
  // White lines between the cells, a frame around them.
  for (int c = 1; c < m; ++c)
    fill_rect(image, gx0 + c * map.cell, gy0, gx0 + c * map.cell + 1, gy1, kWhite);
  for (int r = 1; r < n; ++r)
    fill_rect(image, gx0, gy0 + r * map.cell, gx1, gy0 + r * map.cell + 1, kWhite);
  frame_rect(image, gx0 - 1, gy0 - 1, gx1, gy1, kFrame);

  for (int r = 0; r < n; ++r) {
    const std::string& s = map.row_names[r];
    font.draw(image, gx0 - 8 - font.text_width(s, name_px),
              gy0 + r * map.cell + map.cell / 2 + (font.ascender(name_px) - 2) / 2, s, name_px,
              kText);
  }
  for (int c = 0; c < m; ++c) {
    const std::string& s = map.column_names[c];
    const int baseline_x =
        gx0 + c * map.cell + map.cell / 2 + (font.ascender(name_px) - font.descender(name_px)) / 2;
    font.draw(image, baseline_x, gy1 + 8 + font.text_width(s, name_px), s, name_px, kText,
              /*vertical=*/true);
  }
  draw_centred(font, image, width / 2, pad + font.ascender(kTitlePx), map.title, kTitlePx, kBlack);
  draw_centred(font, image, (gx0 + gx1) / 2, height - pad - font.descender(kLabelPx), map.x_label,
               kLabelPx, kText);
  draw_vertical_centred(font, image, pad + label_h / 2, (gy0 + gy1) / 2, map.y_label, kLabelPx,
                        kText);
  return image;
}

}  // namespace pillarseg
