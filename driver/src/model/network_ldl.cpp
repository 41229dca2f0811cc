#include "network_ldl.hpp"

#include <Eigen/OrderingMethods>
#include <Eigen/SparseCore>
#include <algorithm>
#include <array>
#include <cmath>

namespace mrskin::model::detail {

namespace {
constexpr std::int64_t kNoParent = -1;
// factorize_skipping_zeros() keeps L's non-zeros apart at some cost a visit. When it kept more
// than 3/4 of L's pattern the skipped work did not pay for it (palm-64x64 with every valve open:
// 7 % more instructions a substep; a palm-shaped test network: slower above about 60 %), so
// the next passes are full ones until it tries again.
constexpr std::array<std::size_t, 2> kFullAboveKeptOf = {3, 4};
constexpr int kFullPassesBetweenProbes = 15;
}  // namespace

SparseLdl::SparseLdl(std::size_t n, std::span<const Pair> pairs)
    : n_(n), new_of_old_(n), diag_slot_(n), pair_slot_(pairs.size()) {
  // Fill-reducing ordering on the full symmetric pattern. AMD returns perm with
  // perm[new] = old (Eigen's SimplicialCholesky convention).
  {
    using SpMat = Eigen::SparseMatrix<double, Eigen::ColMajor, int>;
    std::vector<Eigen::Triplet<double, int>> t;
    t.reserve(n + 2 * pairs.size());
    for (std::size_t i = 0; i < n; ++i) {
      t.emplace_back(static_cast<int>(i), static_cast<int>(i), 1.0);
    }
    for (const Pair& p : pairs) {
      t.emplace_back(static_cast<int>(p.first), static_cast<int>(p.second), 1.0);
      t.emplace_back(static_cast<int>(p.second), static_cast<int>(p.first), 1.0);
    }
    SpMat a(static_cast<int>(n), static_cast<int>(n));
    a.setFromTriplets(t.begin(), t.end());
    Eigen::PermutationMatrix<Eigen::Dynamic, Eigen::Dynamic, int> perm;
    Eigen::AMDOrdering<int> amd;
    amd(a, perm);
    if (static_cast<std::size_t>(perm.size()) == n) {
      for (std::size_t k = 0; k < n; ++k) {
        new_of_old_[static_cast<std::size_t>(perm.indices()[static_cast<int>(k)])] =
            static_cast<std::uint32_t>(k);
      }
    } else {
      for (std::size_t k = 0; k < n; ++k) {
        new_of_old_[k] = static_cast<std::uint32_t>(k);
      }
    }
  }

  // Permuted upper triangle: entry (min, max) of each pair lives in column max.
  std::vector<std::vector<std::uint32_t>> rows(n);
  for (std::size_t i = 0; i < n; ++i) {
    rows[new_of_old_[i]].push_back(new_of_old_[i]);
  }
  for (const Pair& p : pairs) {
    const std::uint32_t a = new_of_old_[p.first];
    const std::uint32_t b = new_of_old_[p.second];
    rows[std::max(a, b)].push_back(std::min(a, b));
  }
  ap_.assign(n + 1, 0);
  for (std::size_t k = 0; k < n; ++k) {
    std::sort(rows[k].begin(), rows[k].end());
    rows[k].erase(std::unique(rows[k].begin(), rows[k].end()), rows[k].end());
    ap_[k + 1] = ap_[k] + static_cast<std::uint32_t>(rows[k].size());
    ai_.insert(ai_.end(), rows[k].begin(), rows[k].end());
  }
  ax_.assign(ai_.size(), 0.0);
  auto slot = [&](std::uint32_t r, std::uint32_t c) {
    const auto first = ai_.begin() + ap_[c];
    const auto last = ai_.begin() + ap_[c + 1];
    return static_cast<std::size_t>(std::lower_bound(first, last, r) - ai_.begin());
  };
  for (std::size_t i = 0; i < n; ++i) {
    diag_slot_[i] = slot(new_of_old_[i], new_of_old_[i]);
  }
  for (std::size_t k = 0; k < pairs.size(); ++k) {
    const std::uint32_t a = new_of_old_[pairs[k].first];
    const std::uint32_t b = new_of_old_[pairs[k].second];
    pair_slot_[k] = slot(std::min(a, b), std::max(a, b));
  }

  // Symbolic: elimination tree and column counts of L (ldl_symbolic).
  parent_.assign(n, kNoParent);
  std::vector<std::uint32_t> lnz(n, 0);
  std::vector<std::uint32_t> flag(n, 0);
  for (std::size_t k = 0; k < n; ++k) {
    flag[k] = static_cast<std::uint32_t>(k);
    for (std::uint32_t p = ap_[k]; p < ap_[k + 1]; ++p) {
      std::size_t i = ai_[p];
      if (i >= k) {
        continue;
      }
      while (flag[i] != k) {
        if (parent_[i] == kNoParent) {
          parent_[i] = static_cast<std::int64_t>(k);
        }
        ++lnz[i];
        flag[i] = static_cast<std::uint32_t>(k);
        i = static_cast<std::size_t>(parent_[i]);
      }
    }
  }
  lp_.assign(n + 1, 0);
  for (std::size_t k = 0; k < n; ++k) {
    lp_[k + 1] = lp_[k] + lnz[k];
  }
  li_.assign(lp_[n], 0);
  lx_.assign(lp_[n], 0.0);
  d_.assign(n, 0.0);
  y_.assign(n, 0.0);
  w_.assign(n, 0.0);
  plan_numeric(flag);
  nz_row_.assign(lp_[n], 0);
  nz_value_.assign(lp_[n], 0.0);
  nz_count_.assign(n, 0);
}

void SparseLdl::plan_numeric(std::vector<std::uint32_t>& flag) {
  const std::size_t n = n_;
  // The numeric pass's bookkeeping, done once: ldl_numeric's row patterns (the etree reach of
  // each row, in the order it visits them) and the slot of L each visit writes. The pattern
  // is fixed, so factorize() replays the same arithmetic in the same order without walking
  // the tree again (about half of its instructions on the 5 x 5's 26 nodes).
  std::vector<std::uint32_t> filled(n, 0);
  std::vector<std::uint32_t> pattern(n, 0);
  row_begin_.assign(n + 1, 0);
  for (std::size_t k = 0; k < n; ++k) {
    std::size_t top = n;
    flag[k] = static_cast<std::uint32_t>(k + n);  // a stamp the symbolic pass never used
    for (std::uint32_t p = ap_[k]; p < ap_[k + 1]; ++p) {
      std::size_t i = ai_[p];
      std::size_t len = 0;
      while (flag[i] != k + n) {
        pattern[len++] = static_cast<std::uint32_t>(i);
        flag[i] = static_cast<std::uint32_t>(k + n);
        i = static_cast<std::size_t>(parent_[i]);
      }
      while (len > 0) {
        pattern[--top] = pattern[--len];
      }
    }
    for (; top < n; ++top) {
      const std::uint32_t i = pattern[top];
      const std::uint32_t written = lp_[i] + filled[i]++;
      li_[written] = static_cast<std::uint32_t>(k);
      visits_.push_back({i, lp_[i], written});
    }
    row_begin_[k + 1] = static_cast<std::uint32_t>(visits_.size());
  }
}

std::size_t SparseLdl::row_work(std::size_t k) const noexcept {
  std::size_t work = ap_[k + 1] - ap_[k];
  for (std::uint32_t v = row_begin_[k]; v < row_begin_[k + 1]; ++v) {
    work += 1 + (visits_[v].slot - visits_[v].first);
  }
  return work;
}

bool SparseLdl::factorize() noexcept { return factorize_rows(0, n_); }

bool SparseLdl::factorize_rows(std::size_t first, std::size_t last) noexcept {
  // ldl_numeric, row k of L by a sparse triangular solve, along the precomputed row patterns.
  // Each row leaves the workspace y at zero, so the rows may be factorised apart, in order.
  double* const y = y_.data();
  double* const lx = lx_.data();
  const std::uint32_t* const li = li_.data();
  const double* const ax = ax_.data();
  const std::uint32_t* const ai = ai_.data();
  const Visit* const visits = visits_.data();
  nz_valid_ = false;
  for (std::size_t k = first; k < last; ++k) {
    for (std::uint32_t p = ap_[k]; p < ap_[k + 1]; ++p) {
      y[ai[p]] += ax[p];
    }
    double dk = y[k];
    y[k] = 0.0;
    for (const Visit* v = visits + row_begin_[k]; v != visits + row_begin_[k + 1]; ++v) {
      const double yi = y[v->column];
      y[v->column] = 0.0;
      const std::uint32_t* r = li + v->first;
      const double* l = lx + v->first;
      for (const double* end = lx + v->slot; l != end; ++l, ++r) {
        y[*r] -= *l * yi;
      }
      const double l_ki = yi / d_[v->column];
      dk -= l_ki * yi;
      lx[v->slot] = l_ki;
    }
    if (!(dk > 0.0) || !std::isfinite(dk)) {
      return false;
    }
    d_[k] = dk;
  }
  return true;
}

bool SparseLdl::factorize_skipping_zeros() noexcept {
  // factorize_rows() along the same visits; a column's entries above row k are its non-zeros so
  // far (the rows before k, in order), and a visit whose multiplier is zero only wrote zeros.
  const std::size_t n = n_;
  double* const y = y_.data();
  std::uint32_t* const nz_row = nz_row_.data();
  double* const nz_value = nz_value_.data();
  std::uint32_t* const nz_count = nz_count_.data();
  const std::uint32_t* const lp = lp_.data();
  const double* const ax = ax_.data();
  const std::uint32_t* const ai = ai_.data();
  const Visit* const visits = visits_.data();
  if (full_passes_ahead_ > 0) {
    --full_passes_ahead_;
    return factorize_rows(0, n);
  }
  nz_valid_ = false;
  std::fill(nz_count_.begin(), nz_count_.end(), 0U);
  for (std::size_t k = 0; k < n; ++k) {
    for (std::uint32_t p = ap_[k]; p < ap_[k + 1]; ++p) {
      y[ai[p]] += ax[p];
    }
    double dk = y[k];
    y[k] = 0.0;
    for (const Visit* v = visits + row_begin_[k]; v != visits + row_begin_[k + 1]; ++v) {
      const std::uint32_t i = v->column;
      const double yi = y[i];
      y[i] = 0.0;
      if (yi == 0.0) {
        continue;
      }
      const std::uint32_t first = lp[i];
      const std::uint32_t count = nz_count[i];
      for (std::uint32_t e = first; e < first + count; ++e) {
        y[nz_row[e]] -= nz_value[e] * yi;
      }
      const double l_ki = yi / d_[i];
      dk -= l_ki * yi;
      if (l_ki != 0.0) {
        nz_row[first + count] = static_cast<std::uint32_t>(k);
        nz_value[first + count] = l_ki;
        nz_count[i] = count + 1;
      }
    }
    if (!(dk > 0.0) || !std::isfinite(dk)) {
      return false;
    }
    d_[k] = dk;
  }
  nz_valid_ = true;
  kept_nonzeros_ = 0;
  for (std::size_t i = 0; i < n; ++i) {
    kept_nonzeros_ += nz_count[i];
  }
  if (kept_nonzeros_ * kFullAboveKeptOf[1] > lx_.size() * kFullAboveKeptOf[0]) {
    full_passes_ahead_ = kFullPassesBetweenProbes;
  }
  return true;
}

void SparseLdl::solve_skipping_zeros(std::span<double> x) noexcept {
  if (!nz_valid_) {
    solve(x);
    return;
  }
  const std::size_t n = n_;
  double* const w = w_.data();
  const std::uint32_t* const nz_row = nz_row_.data();
  const double* const nz_value = nz_value_.data();
  const std::uint32_t* const nz_count = nz_count_.data();
  const std::uint32_t* const lp = lp_.data();
  for (std::size_t i = 0; i < n; ++i) {
    w[new_of_old_[i]] = x[i];
  }
  for (std::size_t j = 0; j < n; ++j) {
    const double yj = w[j];
    if (yj == 0.0) {
      continue;
    }
    for (std::uint32_t e = lp[j]; e < lp[j] + nz_count[j]; ++e) {
      w[nz_row[e]] -= nz_value[e] * yj;
    }
  }
  for (std::size_t j = 0; j < n; ++j) {
    w[j] /= d_[j];
  }
  for (std::size_t j = n; j-- > 0;) {
    double yj = w[j];
    for (std::uint32_t e = lp[j]; e < lp[j] + nz_count[j]; ++e) {
      yj -= nz_value[e] * w[nz_row[e]];
    }
    w[j] = yj;
  }
  for (std::size_t i = 0; i < n; ++i) {
    x[i] = w[new_of_old_[i]];
  }
}

void SparseLdl::solve(std::span<double> x) noexcept {
  const std::size_t n = n_;
  double* const w = w_.data();
  const double* const lx = lx_.data();
  const std::uint32_t* const li = li_.data();
  const std::uint32_t* const lp = lp_.data();
  for (std::size_t i = 0; i < n; ++i) {
    w[new_of_old_[i]] = x[i];
  }
  for (std::size_t j = 0; j < n; ++j) {
    const double yj = w[j];
    for (std::uint32_t p = lp[j]; p < lp[j + 1]; ++p) {
      w[li[p]] -= lx[p] * yj;
    }
  }
  for (std::size_t j = 0; j < n; ++j) {
    w[j] /= d_[j];
  }
  for (std::size_t j = n; j-- > 0;) {
    double yj = w[j];
    for (std::uint32_t p = lp[j]; p < lp[j + 1]; ++p) {
      yj -= lx[p] * w[li[p]];
    }
    w[j] = yj;
  }
  for (std::size_t i = 0; i < n; ++i) {
    x[i] = w[new_of_old_[i]];
  }
}

}  // namespace mrskin::model::detail
