// Sparse LDL^T factorisation of the network's step matrix (symmetric positive definite).
//
// The pattern is fixed by the hydraulic graph, so everything that allocates happens once, in the
// constructor: a fill-reducing ordering (Eigen's AMD), the elimination tree and the column
// counts of L (Davis' LDL algorithm, "Algorithm 849", ACM TOMS 31 (2005) 587). factorize() and
// solve() then only touch preallocated arrays: no heap, no exceptions. Eigen's own
// SimplicialLDLT allocates a permuted copy of the matrix on every factorize(), which the
// stepper's "nothing allocates after construction" rules out.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <utility>
#include <vector>

namespace mrskin::model::detail {

class SparseLdl {
 public:
  using Pair = std::pair<std::uint32_t, std::uint32_t>;
  // n unknowns; the off-diagonal pattern as unordered pairs (i != j; repeats allowed, they share a
  // slot). Throws std::bad_alloc only.
  SparseLdl(std::size_t n, std::span<const Pair> pairs);

  [[nodiscard]] std::size_t size() const noexcept { return n_; }
  // Where the caller writes the matrix: values()[diagonal_slot(i)] is A(i, i),
  // values()[pair_slot(k)] is A(i, j) of pairs[k].
  [[nodiscard]] std::size_t diagonal_slot(std::size_t i) const noexcept { return diag_slot_[i]; }
  [[nodiscard]] std::size_t pair_slot(std::size_t k) const noexcept { return pair_slot_[k]; }
  [[nodiscard]] std::span<double> values() noexcept { return ax_; }
  // Non-zeros of L (below the diagonal), for reports.
  [[nodiscard]] std::size_t factor_nonzeros() const noexcept { return lx_.size(); }

  // Numeric factorisation of values(). false if a pivot is not positive and finite.
  bool factorize() noexcept;
  // Rows [first, last) of the factorisation, after rows [0, first): factorize() is all n rows.
  bool factorize_rows(std::size_t first, std::size_t last) noexcept;
  // factorize() and solve() for a matrix with many zeros off its diagonal. Under the exact law a
  // locked passage conducts nothing, so on a large grid with a few cells pressed most nodes stand
  // alone (palm-64x64, a 5 % press, valves at 30 %: 75-93 % of its links conduct nothing), and
  // factorize() spends most of its work multiplying zeros. This pass keeps each column of L as its non-zeros
  // only, in the same row order, and skips a row's visit to a column whose multiplier is zero: the same
  // arithmetic on the non-zeros in the same order, so every non-zero of L, D and the solution
  // has the bits factorize() and solve() give (only the sign of an exact zero may differ).
  // When a pass keeps more than 3/4 of L's pattern (most passages open), the next 15 are full
  // factorize() passes: the same bits either way, at the full pass's cost. solve_skipping_zeros()
  // uses the last factorize_skipping_zeros() that skipped; after any other factorisation it is
  // solve().
  bool factorize_skipping_zeros() noexcept;
  // Non-zeros of L the last factorize_skipping_zeros() kept (of factor_nonzeros()).
  [[nodiscard]] std::size_t kept_nonzeros() const noexcept { return kept_nonzeros_; }
  void solve_skipping_zeros(std::span<double> x) noexcept;
  // Row k's share of factorize()'s work (entries read and multiply-adds), for planning.
  [[nodiscard]] std::size_t row_work(std::size_t k) const noexcept;
  // solve()'s work: entries of L read twice, plus the permutation and D.
  [[nodiscard]] std::size_t solve_work() const noexcept { return 2 * lx_.size() + 3 * n_; }
  // x <- A^-1 x, with the last successful factorisation.
  void solve(std::span<double> x) noexcept;

 private:
  // The row patterns and L slots factorize() replays (flag: the symbolic pass's stamps, < n).
  void plan_numeric(std::vector<std::uint32_t>& flag);

  std::size_t n_;
  std::vector<std::uint32_t> new_of_old_;  // fill-reducing permutation
  // Upper triangle (diagonal included) of the permuted matrix, compressed by column.
  std::vector<std::uint32_t> ap_;
  std::vector<std::uint32_t> ai_;
  std::vector<double> ax_;
  std::vector<std::size_t> diag_slot_;
  std::vector<std::size_t> pair_slot_;
  // L (strictly lower, by column), D, the elimination tree and workspaces.
  std::vector<std::uint32_t> lp_;
  std::vector<std::uint32_t> li_;
  std::vector<double> lx_;
  std::vector<double> d_;
  std::vector<std::int64_t> parent_;
  // The numeric pass's visits, row by row: column i of L and the slot row k writes in it.
  struct Visit {
    std::uint32_t column;  // i
    std::uint32_t first;   // lp_[i]: the entries of column i above row k's run from here
    std::uint32_t slot;    // ... to here, where L(k, i) goes
  };
  std::vector<std::uint32_t> row_begin_;
  std::vector<Visit> visits_;
  std::vector<double> y_;
  std::vector<double> w_;  // solve()'s permuted right-hand side
  // factorize_skipping_zeros()'s L: column i's non-zeros (rows, values) from lp_[i], nz_count_[i]
  // of them.
  std::vector<std::uint32_t> nz_row_;
  std::vector<double> nz_value_;
  std::vector<std::uint32_t> nz_count_;
  bool nz_valid_ = false;
  std::size_t kept_nonzeros_ = 0;
  int full_passes_ahead_ = 0;
};

}  // namespace mrskin::model::detail
