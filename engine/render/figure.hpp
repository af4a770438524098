// The picture of `pillarseg render`, laid out like the paper's Fig. 3: top-view panels of one
// scan (each (H, W) cells at one pixel a cell, scaled up by one whole factor so that a panel is
// at least 1000 pixels wide), each under its title, then a legend of the 12 classes (colour
// swatch and name) and a scale bar in metres. Text by FreeType (engine/render/plot.hpp), so this
// lives in the plot library, outside libpillarseg.so.
#pragma once

#include <string>
#include <vector>

#include "core/classes.hpp"
#include "engine/render/plot.hpp"
#include "engine/util/image.hpp"

namespace pillarseg {

inline constexpr int kFigureMinPanelWidth = 1000;  // pixels
inline constexpr int kFigureMargin = 12;           // pixels of white around everything

// The smallest whole factor that makes a panel of grid_width cells at least 1000 pixels wide
// (1 at the paper's 1000-cell grid, 4 at 250 cells).
int figure_scale(int grid_width);
// The scale bar's length: 10 m, or on a panel narrower than 40 m the largest 1, 2 or 5 times a
// power of ten metres that is at most a quarter of the panel's width.
double scale_bar_metres(double panel_metres);
// Each pixel repeated factor x factor times.
ImageRgb upscale(const ImageRgb& image, int factor);

struct TitledPanel {
  std::string title;
  ImageRgb image;  // one pixel a cell
};

// A rectangle of the figure: x, y its top-left pixel.
struct PixelBox {
  int x = 0, y = 0, width = 0, height = 0;
};

struct Figure {
  ImageRgb image;
  int scale = 1;                   // pixels a cell
  std::vector<PixelBox> panels;    // where each panel's (scaled) map lies
  std::vector<PixelBox> swatches;  // the legend's colour swatches, classes 1..12 in order
  PixelBox scale_bar;              // the bar: scale_bar_metres / cell_metres x scale pixels long
  double scale_bar_metres = 0;
};

// Panels of equal size, top to bottom, on white. cell_metres: the grid's cell size.
Figure compose_figure(const std::vector<TitledPanel>& panels, const ClassTable& classes,
                      double cell_metres, const Font& font);

}  // namespace pillarseg
