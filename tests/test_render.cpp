// The figure of `pillarseg render` (engine/render/figure.hpp): the whole-number scale that makes
// a panel at least 1000 pixels wide, the scale bar's length, panels copied pixel for pixel under
// their titles, the legend's swatches in the class colours, and the scale bar's pixels, at the
// paper's 1000 x 500 grid and at small grids.
#include <gtest/gtest.h>

#include <cmath>

#include "core/classes.hpp"
#include "engine/render/figure.hpp"
#include "tests/support/image_checks.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using pillarseg::test::count_dark;
using pillarseg::test::is_white;
using pillarseg::test::error_of;

namespace {

// A panel whose every pixel says where it is: (x mod 251, y mod 241, 7).
ImageRgb coordinate_panel(int width, int height) {
  ImageRgb image(width, height);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      uint8_t* p = image.at(x, y);
      p[0] = static_cast<uint8_t>(x % 251), p[1] = static_cast<uint8_t>(y % 241), p[2] = 7;
    }
  return image;
}

bool has_colour(const ImageRgb& image, int x, int y, Rgb c) {
  const uint8_t* p = image.at(x, y);
  return p[0] == c.r && p[1] == c.g && p[2] == c.b;
}



// Every check of a composed figure that holds at any grid: the panels' pixels are the sources'
// scaled by figure.scale, each title has ink above its panel, the swatches are their classes'
// colours, the scale bar is as long as its metres at this cell size and scale, and the legend and
// bar lie under the panels, inside the image.
void expect_figure(const Figure& f, const std::vector<TitledPanel>& panels, const ClassTable& classes,
                   double cell_metres) {
  const int cells_wide = panels[0].image.width, cells_high = panels[0].image.height;
  EXPECT_EQ(f.image.width, cells_wide * f.scale + 2 * kFigureMargin);
  ASSERT_EQ(f.panels.size(), panels.size());
  int previous_bottom = 0;
  for (size_t i = 0; i < panels.size(); ++i) {
    const PixelBox& box = f.panels[i];
    EXPECT_EQ(box.x, kFigureMargin);
    EXPECT_EQ(box.width, cells_wide * f.scale);
    EXPECT_EQ(box.height, cells_high * f.scale);
    for (int y = 0; y < box.height; y += 7)
      for (int x = 0; x < box.width; x += 5) {
        const uint8_t* want = panels[i].image.at(x / f.scale, y / f.scale);
        ASSERT_TRUE(has_colour(f.image, box.x + x, box.y + y, Rgb{want[0], want[1], want[2]}))
            << "panel " << i << " pixel " << x << ", " << y;
      }
    EXPECT_GT(count_dark(f.image, box.x, previous_bottom, box.x + 300, box.y), 50) << "no title over panel " << i;
    previous_bottom = box.y + box.height;
  }
  ASSERT_EQ(f.swatches.size(), static_cast<size_t>(kNumClasses));
  for (int k = 1; k <= kNumClasses; ++k) {
    const PixelBox& s = f.swatches[static_cast<size_t>(k - 1)];
    EXPECT_GT(s.y, previous_bottom);
    EXPECT_LT(s.x + s.width, f.image.width);
    for (int y = s.y; y < s.y + s.height; ++y)
      for (int x = s.x; x < s.x + s.width; ++x)
        ASSERT_TRUE(has_colour(f.image, x, y, classes.color(k))) << classes.name(k) << " swatch at " << x << ", " << y;
    EXPECT_GT(count_dark(f.image, s.x + s.width + 4, s.y, s.x + s.width + 60, s.y + s.height), 20)
        << "no name beside the " << classes.name(k) << " swatch";
  }
  const PixelBox& bar = f.scale_bar;
  EXPECT_EQ(bar.width, std::lround(f.scale_bar_metres / cell_metres * f.scale));
  EXPECT_GT(bar.y, f.swatches.back().y + f.swatches.back().height);
  EXPECT_LT(bar.y + bar.height, f.image.height);
  const int middle = bar.y + bar.height / 2;
  for (int x = bar.x; x < bar.x + bar.width; ++x) ASSERT_FALSE(is_white(f.image, x, middle)) << "bar pixel " << x;
  EXPECT_TRUE(is_white(f.image, bar.x - 1, middle));
  EXPECT_TRUE(is_white(f.image, bar.x + bar.width, middle));
  EXPECT_GT(count_dark(f.image, bar.x + bar.width, bar.y - 6, bar.x + bar.width + 80, bar.y + bar.height + 6), 20)
      << "no label beside the scale bar";
}

}  // namespace

TEST(RenderFigure, ScaleReachesAThousandPixelsByWholeFactors) {
  EXPECT_EQ(figure_scale(1000), 1);  // the paper's grid: one pixel a cell
  EXPECT_EQ(figure_scale(2000), 1);
  EXPECT_EQ(figure_scale(250), 4);   // small_cpu.yaml: 0.4 m cells
  EXPECT_EQ(figure_scale(300), 4);   // 3 x 300 = 900 is short of 1000
  EXPECT_EQ(figure_scale(999), 2);
  EXPECT_EQ(figure_scale(1), 1000);
  EXPECT_NE(error_of([] { figure_scale(0); }).find("a grid 0 cells wide"), std::string::npos);
}

TEST(RenderFigure, ScaleBarIsTenMetresOrAQuarterOfANarrowPanel) {
  EXPECT_DOUBLE_EQ(scale_bar_metres(100), 10);  // the paper's 100 m
  EXPECT_DOUBLE_EQ(scale_bar_metres(40), 10);
  EXPECT_DOUBLE_EQ(scale_bar_metres(39), 5);    // a quarter: 9.75
  EXPECT_DOUBLE_EQ(scale_bar_metres(20), 5);
  EXPECT_DOUBLE_EQ(scale_bar_metres(12), 2);    // 3
  EXPECT_DOUBLE_EQ(scale_bar_metres(4), 1);
  EXPECT_DOUBLE_EQ(scale_bar_metres(2), 0.5);
  EXPECT_NE(error_of([] { scale_bar_metres(0); }).find("a panel 0 m wide"), std::string::npos);
}

TEST(RenderFigure, UpscaleRepeatsEachPixel) {
  const ImageRgb small = coordinate_panel(3, 2);
  const ImageRgb big = upscale(small, 3);
  ASSERT_EQ(big.width, 9);
  ASSERT_EQ(big.height, 6);
  for (int y = 0; y < 6; ++y)
    for (int x = 0; x < 9; ++x) {
      const uint8_t* want = small.at(x / 3, y / 3);
      EXPECT_TRUE(has_colour(big, x, y, Rgb{want[0], want[1], want[2]})) << x << ", " << y;
    }
  EXPECT_EQ(upscale(small, 1).pixels, small.pixels);
}

TEST(RenderFigure, PapersGridOnePixelACellTenMetreBar) {
  const Font font(find_font());
  const ClassTable classes = ClassTable::defaults();
  const std::vector<TitledPanel> panels{{"Points", coordinate_panel(1000, 500)},
                                        {"Sparse ground truth", coordinate_panel(1000, 500)}};
  const Figure f = compose_figure(panels, classes, 0.1, font);
  EXPECT_EQ(f.scale, 1);
  EXPECT_EQ(f.image.width, 1024);
  EXPECT_DOUBLE_EQ(f.scale_bar_metres, 10);
  EXPECT_EQ(f.scale_bar.width, 100);  // 10 m / 0.1 m x 1
  expect_figure(f, panels, classes, 0.1);
}

TEST(RenderFigure, SmallGridsScaleUp) {
  const Font font(find_font());
  const ClassTable classes = ClassTable::defaults();
  // small_cpu.yaml: 250 x 125 cells of 0.4 m, scaled by 4.
  const std::vector<TitledPanel> cpu{{"Points", coordinate_panel(250, 125)}, {"Prediction", coordinate_panel(250, 125)}};
  const Figure f = compose_figure(cpu, classes, 0.4, font);
  EXPECT_EQ(f.scale, 4);
  EXPECT_EQ(f.image.width, 1024);
  EXPECT_EQ(f.panels[1].height, 500);
  EXPECT_EQ(f.scale_bar.width, 100);  // 10 m / 0.4 m x 4
  expect_figure(f, cpu, classes, 0.4);
  // 60 x 30 cells of 0.2 m (12 m wide): scale 17 (1020 pixels), a 2 m bar of 2 / 0.2 x 17 pixels.
  const std::vector<TitledPanel> tiny{{"Observability", coordinate_panel(60, 30)}};
  const Figure t = compose_figure(tiny, classes, 0.2, font);
  EXPECT_EQ(t.scale, 17);
  EXPECT_EQ(t.image.width, 1020 + 2 * kFigureMargin);
  EXPECT_DOUBLE_EQ(t.scale_bar_metres, 2);
  EXPECT_EQ(t.scale_bar.width, 170);
  expect_figure(t, tiny, classes, 0.2);
  // The classes' colours come from the table: another colour, another swatch.
  ClassTable edited = classes;
  edited.set_color(5, Rgb{1, 2, 3});
  const Figure e = compose_figure(tiny, edited, 0.2, font);
  const PixelBox& road = e.swatches[4];
  EXPECT_TRUE(has_colour(e.image, road.x + 3, road.y + 3, Rgb{1, 2, 3}));
}

TEST(RenderFigure, PanelsOfDifferentSizesAreRefused) {
  const Font font(find_font());
  const std::vector<TitledPanel> panels{{"Points", coordinate_panel(100, 50)}, {"Prediction", coordinate_panel(100, 40)}};
  const std::string e = error_of([&] { compose_figure(panels, ClassTable::defaults(), 0.4, font); });
  EXPECT_NE(e.find("panel 'Prediction' is 100x40, the first 100x50"), std::string::npos) << e;
  EXPECT_NE(error_of([&] { compose_figure({}, ClassTable::defaults(), 0.4, font); }).find("no panels"),
            std::string::npos);
}
