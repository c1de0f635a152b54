// Multi-level trilinear feature grids on the CPU: forward and backward in one pass each.
//
// Same sampling as torch's grid_sample(mode="bilinear", padding_mode="zeros", align_corners=True)
// on a channel-last table: level l is a [R_l, R_l, R_l, C] table indexed [z][y][x][c]; a point's
// coordinate u in [-1, 1] maps to (u + 1) / 2 * (R - 1); corners outside the table read zero.
// A level whose table has fewer rows than R^3 cells is hashed (instant-NGP's spatial hash, the
// same function as grid_encoding.py's torch path): cell (x, y, z) reads row
// (x ^ y * 2654435761 ^ z * 805459861) mod rows, in uint32 arithmetic.
// Why not grid_sample: its CPU 3D kernel runs one thread per batch item (here: one), reads the C
// channels of a corner R^3 floats apart, and its backward walks the points once per level.
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

struct Corner {
  int64_t offset;  // index of the corner's first channel in the table, -1 = outside
  float w;         // trilinear weight
  float dw[3];     // d w / d u (u: the point's coordinate in [-1, 1])
};

// The 8 corners of the cell holding u [3] (x, y, z) in a table of resolution R (with the weights'
// derivatives when kDerivative).
template <bool kDerivative, bool kHashed>
inline void corners(const float* u, int64_t R, int64_t rows, int64_t C, Corner* out) {
  const float scale = 0.5f * float(R - 1);
  int64_t i0[3];
  float f[3];
  for (int k = 0; k < 3; ++k) {
    const float p = (u[k] + 1.f) * scale;
    const float fl = std::floor(p);
    i0[k] = int64_t(fl);
    f[k] = p - fl;
  }
  for (int c = 0; c < 8; ++c) {
    const int bx = c & 1, by = (c >> 1) & 1, bz = (c >> 2) & 1;
    const int64_t ix = i0[0] + bx, iy = i0[1] + by, iz = i0[2] + bz;
    const float wx = bx ? f[0] : 1.f - f[0];
    const float wy = by ? f[1] : 1.f - f[1];
    const float wz = bz ? f[2] : 1.f - f[2];
    Corner& k = out[c];
    const bool inside = ix >= 0 && ix < R && iy >= 0 && iy < R && iz >= 0 && iz < R;
    if (!inside) {
      k.offset = -1;
    } else if (kHashed) {
      const uint32_t h = uint32_t(ix) ^ (uint32_t(iy) * 2654435761u) ^ (uint32_t(iz) * 805459861u);
      k.offset = int64_t(h % uint32_t(rows)) * C;
    } else {
      k.offset = ((iz * R + iy) * R + ix) * C;
    }
    k.w = wx * wy * wz;
    if (kDerivative) {
      const float sx = bx ? scale : -scale, sy = by ? scale : -scale, sz = bz ? scale : -scale;
      k.dw[0] = sx * wy * wz;
      k.dw[1] = wx * sy * wz;
      k.dw[2] = wx * wy * sz;
    }
  }
}

}  // namespace

// u [N,3] in [-1,1]; tables: L tensors [rows_l * C] (contiguous float; rows_l = R_l^3 when dense).
// Returns [N, L*C].
torch::Tensor encode_forward(torch::Tensor u, std::vector<torch::Tensor> tables, std::vector<int64_t> res, int64_t C) {
  TORCH_CHECK(u.is_contiguous() && u.scalar_type() == torch::kFloat && u.dim() == 2 && u.size(1) == 3, "u must be contiguous float [N,3]");
  const int64_t N = u.size(0), L = int64_t(tables.size());
  auto out = torch::empty({N, L * C}, u.options());
  std::vector<const float*> tab(L);
  std::vector<int64_t> rows(L);
  for (int64_t l = 0; l < L; ++l) {
    tab[l] = tables[l].data_ptr<float>();
    rows[l] = tables[l].numel() / C;
  }
  const float* up = u.data_ptr<float>();
  float* op = out.data_ptr<float>();
  at::parallel_for(0, N, 256, [&](int64_t b, int64_t e) {
    Corner k[8];
    for (int64_t n = b; n < e; ++n) {
      for (int64_t l = 0; l < L; ++l) {
        if (rows[l] < res[l] * res[l] * res[l]) corners<false, true>(up + 3 * n, res[l], rows[l], C, k);
        else corners<false, false>(up + 3 * n, res[l], rows[l], C, k);
        float* o = op + n * L * C + l * C;
        for (int64_t c = 0; c < C; ++c) o[c] = 0.f;
        for (int j = 0; j < 8; ++j) {
          if (k[j].offset < 0) continue;
          const float* t = tab[l] + k[j].offset;
          for (int64_t c = 0; c < C; ++c) o[c] += k[j].w * t[c];
        }
      }
    }
  });
  return out;
}

// grad_out [N, L*C] -> (grads of the tables (dense, like the tables), grad of u [N,3]).
// Work is split over levels so each table is written by one thread (no atomics).
std::vector<torch::Tensor> encode_backward(torch::Tensor grad_out, torch::Tensor u, std::vector<torch::Tensor> tables,
                                           std::vector<int64_t> res, int64_t C, bool need_u) {
  grad_out = grad_out.contiguous();
  const int64_t N = u.size(0), L = int64_t(tables.size());
  std::vector<torch::Tensor> grads;
  std::vector<float*> gp(L);
  std::vector<const float*> tab(L);
  std::vector<int64_t> rows(L);
  for (int64_t l = 0; l < L; ++l) {
    rows[l] = tables[l].numel() / C;
    grads.push_back(torch::zeros_like(tables[l]));
    gp[l] = grads[l].data_ptr<float>();
    tab[l] = tables[l].data_ptr<float>();
  }
  auto gu_levels = need_u ? torch::zeros({L, N, 3}, u.options()) : torch::Tensor();
  float* gul = need_u ? gu_levels.data_ptr<float>() : nullptr;
  const float* up = u.data_ptr<float>();
  const float* go = grad_out.data_ptr<float>();
  at::parallel_for(0, L, 1, [&](int64_t lb, int64_t le) {
    Corner k[8];
    for (int64_t l = lb; l < le; ++l) {
      for (int64_t n = 0; n < N; ++n) {
        const float* g = go + n * L * C + l * C;
        const bool hashed = rows[l] < res[l] * res[l] * res[l];
        if (need_u) {
          if (hashed) corners<true, true>(up + 3 * n, res[l], rows[l], C, k);
          else corners<true, false>(up + 3 * n, res[l], rows[l], C, k);
        } else {
          if (hashed) corners<false, true>(up + 3 * n, res[l], rows[l], C, k);
          else corners<false, false>(up + 3 * n, res[l], rows[l], C, k);
        }
        float d0 = 0.f, d1 = 0.f, d2 = 0.f;
        for (int j = 0; j < 8; ++j) {
          if (k[j].offset < 0) continue;
          float* t = gp[l] + k[j].offset;
          const float* v = tab[l] + k[j].offset;
          float dot = 0.f;
          for (int64_t c = 0; c < C; ++c) {
            t[c] += k[j].w * g[c];
            dot += g[c] * v[c];
          }
          if (!need_u) continue;
          d0 += k[j].dw[0] * dot;
          d1 += k[j].dw[1] * dot;
          d2 += k[j].dw[2] * dot;
        }
        if (gul) {
          float* d = gul + (l * N + n) * 3;
          d[0] = d0; d[1] = d1; d[2] = d2;
        }
      }
    }
  });
  if (need_u) grads.push_back(gu_levels.sum(0));
  return grads;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &encode_forward, "multi-level trilinear grid encoding (CPU)");
  m.def("backward", &encode_backward, "its backward (CPU)");
}
