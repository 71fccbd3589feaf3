//! The workspace discretisation: a `rows x cols` raster of square cells.
//!
//! Every field in hetfleet is a flat `Vec<f64>` in row-major (C) order, `i = row * cols + col`,
//! which is what numpy's `reshape(-1)` of a `(rows, cols)` array gives. Cell `(row, col)` has its
//! centre at `((col + 0.5) * cell_m, (row + 0.5) * cell_m)` metres from the workspace corner.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// A cell by row and column.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Cell {
    pub row: usize,
    pub col: usize,
}

impl Cell {
    pub const fn new(row: usize, col: usize) -> Self {
        Self { row, col }
    }
}

#[derive(Debug, Error, PartialEq)]
pub enum GridError {
    #[error("a grid needs at least one row and one column (got {rows} x {cols})")]
    Empty { rows: usize, cols: usize },
    #[error("cell size must be finite and positive (got {0} m)")]
    CellSize(f64),
    #[error("field has {got} values but the {rows} x {cols} grid has {expected} cells")]
    Length {
        got: usize,
        expected: usize,
        rows: usize,
        cols: usize,
    },
    #[error("stride must be at least 1")]
    Stride,
    #[error("grids cover different extents ({a_w} x {a_h} m vs {b_w} x {b_h} m)")]
    Extent { a_w: f64, a_h: f64, b_w: f64, b_h: f64 },
}

/// A rectangular workspace of `rows x cols` square cells of side `cell_m` metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Grid {
    /// Rows of cells along y (a cell's flat index is `row * cols + col`).
    pub rows: usize,
    /// Columns of cells along x.
    pub cols: usize,
    /// Side of one cell in metres.
    pub cell_m: f64,
}

impl Grid {
    pub fn new(rows: usize, cols: usize, cell_m: f64) -> Result<Self, GridError> {
        if rows == 0 || cols == 0 {
            return Err(GridError::Empty { rows, cols });
        }
        if !(cell_m.is_finite() && cell_m > 0.0) {
            return Err(GridError::CellSize(cell_m));
        }
        Ok(Self { rows, cols, cell_m })
    }

    /// Number of cells `N`.
    pub fn len(&self) -> usize {
        self.rows * self.cols
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn width_m(&self) -> f64 {
        self.cols as f64 * self.cell_m
    }

    pub fn height_m(&self) -> f64 {
        self.rows as f64 * self.cell_m
    }

    /// Flat row-major index of a cell (the cell must be inside the grid).
    pub fn index(&self, c: Cell) -> usize {
        debug_assert!(self.contains(c));
        c.row * self.cols + c.col
    }

    /// The cell of a flat index.
    pub fn cell(&self, i: usize) -> Cell {
        debug_assert!(i < self.len());
        Cell::new(i / self.cols, i % self.cols)
    }

    pub fn contains(&self, c: Cell) -> bool {
        c.row < self.rows && c.col < self.cols
    }

    /// Centre of a cell in metres, `(x, y)` with x along columns.
    pub fn centre_m(&self, c: Cell) -> (f64, f64) {
        ((c.col as f64 + 0.5) * self.cell_m, (c.row as f64 + 0.5) * self.cell_m)
    }

    /// The cell containing a point in metres, or `None` outside the workspace.
    pub fn cell_at(&self, x_m: f64, y_m: f64) -> Option<Cell> {
        if !(x_m.is_finite() && y_m.is_finite()) || x_m < 0.0 || y_m < 0.0 {
            return None;
        }
        let c = Cell::new((y_m / self.cell_m) as usize, (x_m / self.cell_m) as usize);
        self.contains(c).then_some(c)
    }

    /// Check that a field has one value per cell.
    pub fn check_len(&self, n: usize) -> Result<(), GridError> {
        if n != self.len() {
            return Err(GridError::Length {
                got: n,
                expected: self.len(),
                rows: self.rows,
                cols: self.cols,
            });
        }
        Ok(())
    }

    /// `|grad x|^2` at every cell, per cell (not per metre): central differences inside,
    /// one-sided at the borders (exact for a linear field everywhere).
    pub fn squared_gradient(&self, field: &[f64]) -> Result<Vec<f64>, GridError> {
        self.check_len(field.len())?;
        let slope = |lo: usize, hi: usize, at: &dyn Fn(usize) -> f64| {
            if hi > lo {
                (at(hi) - at(lo)) / (hi - lo) as f64
            } else {
                0.0
            }
        };
        Ok((0..self.len())
            .map(|i| {
                let Cell { row, col } = self.cell(i);
                let along = slope(col.saturating_sub(1), (col + 1).min(self.cols - 1), &|c| {
                    field[row * self.cols + c]
                });
                let across = slope(row.saturating_sub(1), (row + 1).min(self.rows - 1), &|r| {
                    field[r * self.cols + col]
                });
                along * along + across * across
            })
            .collect())
    }

    /// Flat indices of the cells whose centres lie within `radius` cells of `centre`'s centre
    /// (paper eq. sensing-region), clipped at the borders, in increasing index order.
    pub fn disk(&self, centre: Cell, radius: f64) -> Vec<usize> {
        let r = radius.max(0.0);
        let reach = r.floor() as usize;
        let r0 = centre.row.saturating_sub(reach);
        let r1 = (centre.row + reach).min(self.rows - 1);
        let c0 = centre.col.saturating_sub(reach);
        let c1 = (centre.col + reach).min(self.cols - 1);
        let r2 = r * r + 1e-9;
        let mut out = Vec::with_capacity((2 * reach + 1) * (2 * reach + 1));
        for row in r0..=r1 {
            let dr = row as f64 - centre.row as f64;
            for col in c0..=c1 {
                let dc = col as f64 - centre.col as f64;
                if dr * dr + dc * dc <= r2 {
                    out.push(row * self.cols + col);
                }
            }
        }
        out
    }

    /// The coarse grid and values obtained by keeping every `stride`-th cell in each direction,
    /// starting at cell (0, 0). The coarse cells are `stride` times larger and their centres sit
    /// on the kept fine cells' centres' lattice, shifted so both grids cover the same corner.
    pub fn stride_downsample(&self, field: &[f64], stride: usize) -> Result<(StridedGrid, Vec<f64>), GridError> {
        self.check_len(field.len())?;
        let lattice = self.strided(stride)?;
        let out = (0..lattice.rows * lattice.cols)
            .map(|k| field[self.index(lattice.fine_cell(k))])
            .collect();
        Ok((lattice, out))
    }

    /// The lattice of every `stride`-th cell (see [`Self::stride_downsample`]), without data.
    pub fn strided(&self, stride: usize) -> Result<StridedGrid, GridError> {
        if stride == 0 {
            return Err(GridError::Stride);
        }
        Ok(StridedGrid {
            fine: *self,
            stride,
            rows: self.rows.div_ceil(stride),
            cols: self.cols.div_ceil(stride),
        })
    }

    /// Bilinear interpolation of `values`, given at the centres of the cells of `coarse`, onto
    /// the centres of this grid's cells. Both grids must cover the same extent. Points outside
    /// the convex hull of the coarse centres take the value at the nearest point of the hull
    /// (clamped), so nothing is extrapolated from noisy data.
    pub fn upsample_bilinear(&self, coarse: &Grid, values: &[f64]) -> Result<Vec<f64>, GridError> {
        coarse.check_len(values.len())?;
        let tol = 1e-9 * (self.width_m() + self.height_m());
        if (coarse.width_m() - self.width_m()).abs() > tol || (coarse.height_m() - self.height_m()).abs() > tol {
            return Err(GridError::Extent {
                a_w: coarse.width_m(),
                a_h: coarse.height_m(),
                b_w: self.width_m(),
                b_h: self.height_m(),
            });
        }
        // Fractional coarse coordinate of every fine row / column centre (separable).
        let axis = |n_fine: usize, n_coarse: usize| -> Vec<(usize, usize, f64)> {
            (0..n_fine)
                .map(|i| {
                    let u = ((i as f64 + 0.5) * self.cell_m / coarse.cell_m - 0.5).clamp(0.0, (n_coarse - 1) as f64);
                    let i0 = (u.floor() as usize).min(n_coarse - 1);
                    let i1 = (i0 + 1).min(n_coarse - 1);
                    (i0, i1, u - i0 as f64)
                })
                .collect()
        };
        Ok(bilinear(
            &axis(self.rows, coarse.rows),
            &axis(self.cols, coarse.cols),
            coarse.cols,
            values,
            false,
        ))
    }
}

/// The coarse lattice of a stride downsampling: coarse cell `(r, c)` is fine cell
/// `(r * stride, c * stride)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StridedGrid {
    pub fine: Grid,
    pub stride: usize,
    pub rows: usize,
    pub cols: usize,
}

/// A fine row (or column) between two coarse ones: their indices and the second's weight.
type Neighbours = (usize, usize, f64);

impl StridedGrid {
    /// Bilinear interpolation from the kept cells back to every fine cell (clamped beyond the
    /// last kept row / column). Exact for fields bilinear in (row, col) inside the lattice.
    pub fn upsample_bilinear(&self, values: &[f64]) -> Result<Vec<f64>, GridError> {
        self.check_coarse_len(values.len())?;
        let (rows, cols) = self.axes();
        Ok(bilinear(&rows, &cols, self.cols, values, false))
    }

    /// The variance of [`Self::upsample_bilinear`]'s output when the coarse values carry
    /// independent errors of variance `variance`: each fine cell gets `sum_i w_i^2 var_i` over
    /// its bilinear weights `w_i`.
    pub fn upsample_variance(&self, variance: &[f64]) -> Result<Vec<f64>, GridError> {
        self.check_coarse_len(variance.len())?;
        let (rows, cols) = self.axes();
        Ok(bilinear(&rows, &cols, self.cols, variance, true))
    }

    /// The fine cell a coarse cell sits on.
    pub fn fine_cell(&self, coarse_index: usize) -> Cell {
        Cell::new(
            (coarse_index / self.cols) * self.stride,
            (coarse_index % self.cols) * self.stride,
        )
    }

    /// The coarse index of a fine cell, if the lattice has a node on it.
    pub fn coarse_index(&self, cell: Cell) -> Option<usize> {
        (cell.row.is_multiple_of(self.stride) && cell.col.is_multiple_of(self.stride))
            .then(|| (cell.row / self.stride) * self.cols + cell.col / self.stride)
    }

    fn check_coarse_len(&self, n: usize) -> Result<(), GridError> {
        if n != self.rows * self.cols {
            return Err(GridError::Length {
                got: n,
                expected: self.rows * self.cols,
                rows: self.rows,
                cols: self.cols,
            });
        }
        Ok(())
    }

    /// [`Self::upsample_bilinear`] of the fine rows from `row0` and the fine columns from `col0`
    /// only (row-major over that corner), each value as the whole upsampling makes it.
    pub fn upsample_bilinear_from(&self, values: &[f64], row0: usize, col0: usize) -> Result<Vec<f64>, GridError> {
        self.check_coarse_len(values.len())?;
        let (rows, cols) = self.axes();
        let (rows, cols) = (&rows[row0.min(rows.len())..], &cols[col0.min(cols.len())..]);
        Ok(bilinear(rows, cols, self.cols, values, false))
    }

    /// Per fine row and per fine column: the two coarse neighbours and the weight of the second.
    fn axes(&self) -> (Vec<Neighbours>, Vec<Neighbours>) {
        let axis = |n_fine: usize, n_coarse: usize| -> Vec<(usize, usize, f64)> {
            (0..n_fine)
                .map(|i| {
                    let u = (i as f64 / self.stride as f64).min((n_coarse - 1) as f64);
                    let i0 = u.floor() as usize;
                    let i1 = (i0 + 1).min(n_coarse - 1);
                    (i0, i1, u - i0 as f64)
                })
                .collect()
        };
        (axis(self.fine.rows, self.rows), axis(self.fine.cols, self.cols))
    }
}

/// Separable bilinear interpolation given, per output row and column, the two coarse neighbours
/// and the weight of the second. With `squared`, the weights are squared (variance propagation
/// for independent errors; at a clamped border the duplicated neighbour has weight 0).
fn bilinear(
    rows: &[(usize, usize, f64)],
    cols: &[(usize, usize, f64)],
    coarse_cols: usize,
    v: &[f64],
    squared: bool,
) -> Vec<f64> {
    let mut out = vec![0.0; rows.len() * cols.len()];
    let w = |a: f64| if squared { a * a } else { a };
    crate::par::chunks_mut(&mut out, cols.len(), 4, |k, row| {
        let (r0, r1, fr) = rows[k];
        for (o, &(c0, c1, fc)) in row.iter_mut().zip(cols) {
            let top = v[r0 * coarse_cols + c0] * w(1.0 - fc) + v[r0 * coarse_cols + c1] * w(fc);
            let bot = v[r1 * coarse_cols + c0] * w(1.0 - fc) + v[r1 * coarse_cols + c1] * w(fc);
            *o = top * w(1.0 - fr) + bot * w(fr);
        }
    });
    out
}

/// Area-weighted average of a `rows x cols` field onto a `to_rows x to_cols` raster covering
/// the same extent (the plasma specification's downsampling: 2x2 blocks from 96 x 384 to
/// 48 x 192, fractional blocks to 10 x 39). Separable: each coarse cell averages the fine cells
/// it overlaps, weighted by the overlapped fraction.
pub fn area_average(
    values: &[f64],
    rows: usize,
    cols: usize,
    to_rows: usize,
    to_cols: usize,
) -> Result<Vec<f64>, GridError> {
    if rows == 0 || cols == 0 || to_rows == 0 || to_cols == 0 {
        return Err(GridError::Empty {
            rows: to_rows.min(rows),
            cols: to_cols.min(cols),
        });
    }
    if values.len() != rows * cols {
        return Err(GridError::Length {
            got: values.len(),
            expected: rows * cols,
            rows,
            cols,
        });
    }
    // Per coarse index: (fine index, weight) with weights summing to 1.
    let axis = |n: usize, m: usize| -> Vec<Vec<(usize, f64)>> {
        (0..m)
            .map(|k| {
                let (a, b) = (k as f64 * n as f64 / m as f64, (k + 1) as f64 * n as f64 / m as f64);
                let mut w = vec![];
                for i in (a.floor() as usize)..(b.ceil() as usize).min(n) {
                    let overlap = (b.min(i as f64 + 1.0) - a.max(i as f64)).max(0.0);
                    if overlap > 0.0 {
                        w.push((i, overlap / (b - a)));
                    }
                }
                w
            })
            .collect()
    };
    let (wr, wc) = (axis(rows, to_rows), axis(cols, to_cols));
    // Columns first (rows x to_cols), then rows.
    let separable = |values: &[f64]| {
        let mut tmp = vec![0.0; rows * to_cols];
        for r in 0..rows {
            for (k, w) in wc.iter().enumerate() {
                tmp[r * to_cols + k] = w.iter().map(|&(c, x)| x * values[r * cols + c]).sum();
            }
        }
        let mut out = vec![0.0; to_rows * to_cols];
        for (k, w) in wr.iter().enumerate() {
            for c in 0..to_cols {
                out[k * to_cols + c] = w.iter().map(|&(r, x)| x * tmp[r * to_cols + c]).sum();
            }
        }
        out
    };
    if !values.iter().any(|v| v.is_nan()) {
        return Ok(separable(values));
    }
    // Missing values (NaN): each coarse cell averages the values it has, weighted by their
    // overlap and renormalised; a coarse cell with none is missing.
    let have: Vec<f64> = values.iter().map(|v| if v.is_nan() { 0.0 } else { 1.0 }).collect();
    let filled: Vec<f64> = values.iter().map(|v| if v.is_nan() { 0.0 } else { *v }).collect();
    let (sum, weight) = (separable(&filled), separable(&have));
    Ok(sum
        .iter()
        .zip(&weight)
        .map(|(s, w)| if *w > 1e-12 { s / w } else { f64::NAN })
        .collect())
}

#[cfg(test)]
mod tests {
    #[test]
    fn squared_gradient_is_exact_on_a_linear_field() {
        let g = super::Grid::new(4, 6, 1.0).unwrap();
        let x: Vec<f64> = (0..g.len())
            .map(|i| 2.0 * g.cell(i).col as f64 - 0.5 * g.cell(i).row as f64 + 3.0)
            .collect();
        assert!(g.squared_gradient(&x).unwrap().iter().all(|v| (v - 4.25).abs() < 1e-12));
        assert!(g.squared_gradient(&x[1..]).is_err());
        let one_row = super::Grid::new(1, 3, 1.0).unwrap();
        assert_eq!(
            one_row.squared_gradient(&[0.0, 1.0, 4.0]).unwrap(),
            vec![1.0, 4.0, 9.0],
            "one-sided at the ends, no slope across a single row"
        );
    }

    use super::*;

    #[test]
    fn area_average_keeps_the_mean_and_averages_blocks() {
        let (rows, cols) = (96, 384);
        let f: Vec<f64> = (0..rows * cols).map(|i| ((i * 7919) % 101) as f64).collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        // 2 x 2 blocks exactly.
        let half = area_average(&f, rows, cols, 48, 192).unwrap();
        assert!((half[0] - (f[0] + f[1] + f[cols] + f[cols + 1]) / 4.0).abs() < 1e-12);
        // Fractional blocks: the mean is kept (equal-area coarse cells).
        for (r, c) in [(48, 192), (10, 39), (7, 5)] {
            let a = area_average(&f, rows, cols, r, c).unwrap();
            assert!((mean(&a) - mean(&f)).abs() < 1e-9, "{r} x {c}");
        }
        assert!(area_average(&f, rows, cols, 0, 3).is_err());
        assert!(area_average(&f[1..], rows, cols, 3, 3).is_err());
    }

    #[test]
    fn index_and_cell_round_trip() {
        let g = Grid::new(7, 11, 2.0).unwrap();
        for i in 0..g.len() {
            assert_eq!(g.index(g.cell(i)), i);
        }
        assert_eq!(g.cell(12), Cell::new(1, 1));
        assert_eq!(g.cell_at(3.0, 1.0), Some(Cell::new(0, 1)));
        assert_eq!(g.cell_at(22.0, 1.0), None);
        assert_eq!(g.cell_at(f64::NAN, 1.0), None);
    }

    #[test]
    fn rejects_bad_grids() {
        assert!(Grid::new(0, 3, 1.0).is_err());
        assert!(Grid::new(3, 3, 0.0).is_err());
        assert!(Grid::new(3, 3, f64::INFINITY).is_err());
    }

    #[test]
    fn disk_is_euclidean_and_clipped() {
        let g = Grid::new(20, 20, 1.0).unwrap();
        // Radius 1: the centre and its 4 neighbours.
        assert_eq!(g.disk(Cell::new(5, 5), 1.0).len(), 5);
        // Radius 2 in the open: the 13 lattice points with dr^2 + dc^2 <= 4.
        assert_eq!(g.disk(Cell::new(5, 5), 2.0).len(), 13);
        // Corner: a quarter of the radius-2 disk, i.e. 6 cells.
        let d = g.disk(Cell::new(0, 0), 2.0);
        assert_eq!(d, vec![0, 1, 2, 20, 21, 40]);
        assert_eq!(g.disk(Cell::new(3, 3), 0.0), vec![63]);
    }

    #[test]
    fn stride_upsampling_is_exact_on_bilinear_fields() {
        let g = Grid::new(13, 17, 1.0).unwrap();
        let f: Vec<f64> = (0..g.len())
            .map(|i| {
                let c = g.cell(i);
                let (r, k) = (c.row as f64, c.col as f64);
                1.5 - 0.3 * r + 0.7 * k + 0.05 * r * k
            })
            .collect();
        let (sg, coarse) = g.stride_downsample(&f, 4).unwrap();
        assert_eq!((sg.rows, sg.cols), (4, 5));
        let up = sg.upsample_bilinear(&coarse).unwrap();
        // Inside the lattice (rows <= 12, cols <= 16 here: everything) it is exact.
        for i in 0..g.len() {
            assert!((up[i] - f[i]).abs() < 1e-12, "cell {i}: {} vs {}", up[i], f[i]);
        }
    }

    #[test]
    fn grid_to_grid_upsampling_is_exact_on_bilinear_fields_inside_the_hull() {
        let fine = Grid::new(24, 48, 1.0).unwrap();
        let coarse = Grid::new(6, 12, 4.0).unwrap();
        let bil = |x: f64, y: f64| 2.0 + 0.1 * x - 0.2 * y + 0.03 * x * y;
        let cv: Vec<f64> = (0..coarse.len())
            .map(|i| {
                let (x, y) = coarse.centre_m(coarse.cell(i));
                bil(x, y)
            })
            .collect();
        let up = fine.upsample_bilinear(&coarse, &cv).unwrap();
        let (lo, hi_x, hi_y) = (2.0, 46.0, 22.0); // first / last coarse centres
        let mut checked = 0;
        for (i, u) in up.iter().enumerate() {
            let (x, y) = fine.centre_m(fine.cell(i));
            if x >= lo && x <= hi_x && y >= lo && y <= hi_y {
                assert!((u - bil(x, y)).abs() < 1e-12);
                checked += 1;
            }
        }
        assert!(checked > fine.len() / 2);
        let other = Grid::new(6, 13, 4.0).unwrap();
        assert!(fine.upsample_bilinear(&other, &vec![0.0; other.len()]).is_err());
    }
}
