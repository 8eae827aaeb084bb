//! Which open incident areas hold a point, found through a uniform latitude/longitude grid so that
//! the per-sample cost does not grow with the number of open incidents (§11 of the detector
//! specification: every sample of every vehicle asks whether it lies in an area).
//!
//! An area is a circle in the metric of [`distance_m`]: the local WGS-84 plane at its centre, the
//! longitude difference wrapped into [-180, 180]. A point inside it therefore differs from the centre
//! by at most `radius / M` in latitude and `radius / (N cos φ)` in longitude (M and N the WGS-84
//! radii at the centre's latitude φ), which gives each area a box in degrees. Every area is entered in
//! the grid cells its box (padded against rounding) overlaps, taken modulo 360° in longitude so that an
//! area across the antimeridian is found from both sides; a lookup reads the one cell of the point,
//! skips the candidates whose box does not hold it and tests the others with [`distance_m`] itself,
//! so the answer is the linear scan's, exactly.
//! Areas the grid cannot hold cheaply are tested for every point, as the linear scan would: those
//! whose box spans more than [`MAX_CELLS_PER_AREA`] cells (a centre within a few tenths of a degree of
//! a pole, where the longitude extent reaches all the way round, or a radius far beyond the
//! correlator's), and those with a centre or radius that is not a finite, valid value. Points outside
//! [-90, 90] × [-180, 180] or not finite (never a validated sample) are answered by the linear scan
//! too.
//!
//! Why a grid rather than an R-tree: the areas are circles of similar size (at most the correlator's
//! radius plus its margin), so a grid sized to them answers with one hash lookup and a handful of
//! distance tests whatever their number, where a tree descends O(log n) levels; the box of an area
//! across the antimeridian has to be split in two for a tree anyway; and the grid needs no dependency
//! in this pure crate. Cells are sized to the median area (its span in latitude, within
//! [`MIN_CELL_DEG`] and [`MAX_CELL_DEG`]), so that most areas fall in a few cells and one outsized
//! area does not coarsen the grid for the others. Rebuilding costs O(cells entered), once per refresh
//! of the open incidents (once a second), not per sample.
//!
//! Owns the index and the point-in-area answer. Must not decide what an incident is, which incidents
//! are open, nor how the answer acts on a detection.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use crate::geo::{LatLon, wgs84_radii};

use super::distance_m;

/// The smallest cell edge (degrees, about 1.1 km of latitude).
pub const MIN_CELL_DEG: f64 = 0.01;
/// The largest cell edge (degrees).
pub const MAX_CELL_DEG: f64 = 10.0;
/// An area whose box spans more cells than this is tested for every point instead.
pub const MAX_CELLS_PER_AREA: u64 = 4096;
/// Relative and absolute padding of an area's box (degrees): far above the rounding of the distance
/// and of the cell arithmetic, far below a cell.
const PAD_RELATIVE: f64 = 1e-9;
const PAD_DEG: f64 = 1e-9;

/// One circle: a centre and a radius in metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Area {
    pub centre: LatLon,
    pub radius_m: f64,
}

impl Area {
    /// Whether `point` lies inside, by [`distance_m`] (the linear scan's test).
    pub fn contains(&self, point: LatLon) -> bool {
        distance_m(self.centre, point) <= self.radius_m
    }
}

/// The open areas, indexed by grid cell. Immutable once built: a refresh builds a new one.
#[derive(Clone, Debug, Default)]
pub struct AreaIndex {
    areas: Vec<Area>,
    /// Cell edge in degrees (latitude and longitude alike); 360 / `columns` exactly.
    cell_deg: f64,
    /// Longitude columns round the globe.
    columns: i64,
    /// Each cell's run in `entries`: (start, length).
    cells: HashMap<u64, (u32, u32), BuildHasherDefault<CellHasher>>,
    /// The areas of each cell with their boxes, grouped by cell.
    entries: Vec<Entry>,
    /// Areas tested for every point (see the module's documentation).
    everywhere: Vec<u32>,
}

impl AreaIndex {
    /// Indexes `areas`.
    pub fn new(areas: Vec<Area>) -> Self {
        let boxes: Vec<Option<AreaBox>> = areas.iter().map(AreaBox::of).collect();
        let cell_target = median_cell(&boxes);
        let columns = (360.0 / cell_target).ceil().max(1.0) as i64;
        let cell_deg = 360.0 / columns as f64;
        let mut everywhere = Vec::new();
        let mut keyed: Vec<(u64, u32)> = Vec::new();
        for (i, area_box) in boxes.iter().enumerate() {
            let i = i as u32;
            match area_box.and_then(|b| b.cells(cell_deg, columns)) {
                Some(span) => {
                    for row in span.rows.0..=span.rows.1 {
                        for column in span.columns(columns) {
                            keyed.push((cell_key(row, column), i));
                        }
                    }
                }
                None => everywhere.push(i),
            }
        }
        keyed.sort_unstable();
        keyed.dedup();
        let mut cells = HashMap::with_capacity_and_hasher(keyed.len(), Default::default());
        let mut entries = Vec::with_capacity(keyed.len());
        for (key, area) in keyed {
            let run = cells.entry(key).or_insert((entries.len() as u32, 0));
            run.1 += 1;
            if let Some(area_box) = boxes[area as usize] {
                entries.push(Entry { area_box, area });
            }
        }
        Self {
            areas,
            cell_deg,
            columns,
            cells,
            entries,
            everywhere,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.areas.is_empty()
    }

    pub fn len(&self) -> usize {
        self.areas.len()
    }

    /// The indexed areas, in the order given.
    pub fn areas(&self) -> &[Area] {
        &self.areas
    }

    /// Whether `point` lies inside any area: the same answer as testing every area with
    /// [`Area::contains`].
    pub fn contains(&self, point: LatLon) -> bool {
        if self.areas.is_empty() {
            return false;
        }
        if !point.is_valid() {
            // Never a validated sample; an infinite coordinate is even inside an infinite radius.
            return self.linear_contains(point);
        }
        let test = |&i: &u32| self.areas[i as usize].contains(point);
        if self.everywhere.iter().any(test) {
            return true;
        }
        let row = (point.lat_deg / self.cell_deg).floor() as i64;
        let column = column_of(point.lon_deg, self.cell_deg, self.columns);
        match self.cells.get(&cell_key(row, column)) {
            // The box first (a few comparisons): only a point inside it can be inside the area.
            Some(&(start, length)) => self.entries[start as usize..(start + length) as usize]
                .iter()
                .any(|entry| entry.area_box.may_hold(point) && test(&entry.area)),
            None => false,
        }
    }

    /// Whether `point` lies inside any area, testing every one (the reference for the index).
    pub fn linear_contains(&self, point: LatLon) -> bool {
        self.areas.iter().any(|area| area.contains(point))
    }

    /// How many areas are tested for every point (not held by the grid).
    pub fn unindexed(&self) -> usize {
        self.everywhere.len()
    }
}

/// An area entered in a cell, with its box.
#[derive(Clone, Copy, Debug)]
struct Entry {
    area_box: AreaBox,
    area: u32,
}

/// An area's box in degrees: latitude bounds (not clipped at the poles), the longitude centre and
/// half-width (≥ 180 meaning all the way round).
#[derive(Clone, Copy, Debug)]
struct AreaBox {
    lat: (f64, f64),
    lon_centre: f64,
    lon_half: f64,
}

/// The cells of a box: rows inclusive, and the column range before wrapping (or all columns).
struct CellSpan {
    rows: (i64, i64),
    /// `None`: every column.
    columns: Option<(i64, i64)>,
}

impl CellSpan {
    fn columns(&self, columns: i64) -> impl Iterator<Item = i64> {
        let (first, last) = self.columns.unwrap_or((0, columns - 1));
        (first..=last).map(move |c| c.rem_euclid(columns))
    }
}

impl AreaBox {
    /// `None` for an area the grid cannot hold: a centre off the globe or a radius that is not a
    /// finite, non-negative number.
    fn of(area: &Area) -> Option<Self> {
        let Area { centre, radius_m } = *area;
        if !centre.is_valid() || !radius_m.is_finite() || radius_m < 0.0 {
            return None;
        }
        let (meridian, prime_vertical) = wgs84_radii(centre.lat_deg);
        let pad = |half_deg: f64| half_deg * (1.0 + PAD_RELATIVE) + PAD_DEG;
        let lat_half = pad((radius_m / meridian).to_degrees());
        let cos = centre.lat_deg.to_radians().cos().abs();
        let lon_half = (radius_m / (prime_vertical * cos)).to_degrees();
        let lon_half = if lon_half.is_finite() {
            pad(lon_half)
        } else {
            f64::INFINITY
        };
        Some(Self {
            lat: (centre.lat_deg - lat_half, centre.lat_deg + lat_half),
            lon_centre: centre.lon_deg,
            lon_half,
        })
    }

    /// Whether `point` (valid) lies in the box, the longitude difference wrapped as
    /// [`distance_m`] wraps it: a point outside is outside the area.
    fn may_hold(&self, point: LatLon) -> bool {
        if point.lat_deg < self.lat.0 || point.lat_deg > self.lat.1 {
            return false;
        }
        let mut difference = point.lon_deg - self.lon_centre;
        if difference > 180.0 {
            difference -= 360.0;
        } else if difference < -180.0 {
            difference += 360.0;
        }
        difference.abs() <= self.lon_half
    }

    /// The cells it overlaps, or `None` when they are more than [`MAX_CELLS_PER_AREA`].
    fn cells(&self, cell_deg: f64, columns: i64) -> Option<CellSpan> {
        let (first_row, last_row) = (
            (self.lat.0 / cell_deg).floor(),
            (self.lat.1 / cell_deg).floor(),
        );
        // Checked in floating point first: a radius far beyond any incident's spans more rows
        // than an integer holds.
        if last_row - first_row + 1.0 > MAX_CELLS_PER_AREA as f64 {
            return None;
        }
        let rows = (first_row as i64, last_row as i64);
        let row_count = (rows.1 - rows.0 + 1) as u64;
        let (column_range, column_count) = if self.lon_half >= 180.0 {
            (None, columns as u64)
        } else {
            let first = ((self.lon_centre - self.lon_half + 180.0) / cell_deg).floor() as i64;
            let last = ((self.lon_centre + self.lon_half + 180.0) / cell_deg).floor() as i64;
            let count = (last - first + 1) as u64;
            if count >= columns as u64 {
                (None, columns as u64)
            } else {
                (Some((first, last)), count)
            }
        };
        (row_count.saturating_mul(column_count) <= MAX_CELLS_PER_AREA).then_some(CellSpan {
            rows,
            columns: column_range,
        })
    }
}

/// The cell edge to aim for: the median span in latitude of the indexable areas.
fn median_cell(boxes: &[Option<AreaBox>]) -> f64 {
    let mut extents: Vec<f64> = boxes.iter().flatten().map(|b| b.lat.1 - b.lat.0).collect();
    if extents.is_empty() {
        return MAX_CELL_DEG;
    }
    let middle = extents.len() / 2;
    let (_, median, _) = extents.select_nth_unstable_by(middle, f64::total_cmp);
    median.clamp(MIN_CELL_DEG, MAX_CELL_DEG)
}

/// The column of a longitude in [-180, 180] (180 is the column of -180).
fn column_of(lon_deg: f64, cell_deg: f64, columns: i64) -> i64 {
    (((lon_deg + 180.0) / cell_deg).floor() as i64).rem_euclid(columns)
}

fn cell_key(row: i64, column: i64) -> u64 {
    ((row as i32 as u32 as u64) << 32) | (column as u32 as u64)
}

/// A multiplicative hash of a cell key (the keys are small integers, never attacker-chosen in bulk:
/// they come from the open incidents).
#[derive(Default)]
struct CellHasher(u64);

impl Hasher for CellHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }

    fn write_u64(&mut self, key: u64) {
        let mixed = (self.0 ^ key).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        self.0 = mixed ^ (mixed >> 29);
    }
}

#[cfg(test)]
mod tests;
