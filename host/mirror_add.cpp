#include "host/mirror_add.hpp"

#include "core/error.hpp"

namespace pillarseg::host {

template <class T>
void mirror_add(const Tensor<T>& x, bool mirror_y, bool mirror_x, Tensor<T>& sum) {
  PS_CHECK(x.rank() == 4 && sum.shape() == x.shape(),
           "mirror_add: expected x and sum of one shape (B, K, H, W), given {} and {}", shape_str(x.shape()),
           shape_str(sum.shape()));
  PS_CHECK(&sum != &x, "mirror_add: sum must not be x");
  const int64_t planes = x.dim(0) * x.dim(1), height = x.dim(2), width = x.dim(3);
  for (int64_t p = 0; p < planes; ++p) {
    for (int64_t iy = 0; iy < height; ++iy) {
      const T* row = x.data() + (p * height + (mirror_y ? height - 1 - iy : iy)) * width;
      T* out = sum.data() + (p * height + iy) * width;
      if (mirror_x) {
        for (int64_t ix = 0; ix < width; ++ix) out[ix] += row[width - 1 - ix];
      } else {
        for (int64_t ix = 0; ix < width; ++ix) out[ix] += row[ix];
      }
    }
  }
}

template void mirror_add<float>(const Tensor<float>&, bool, bool, Tensor<float>&);
template void mirror_add<double>(const Tensor<double>&, bool, bool, Tensor<double>&);

}  // namespace pillarseg::host
