//! A 2-D log-odds occupancy grid stored in square tiles shared copy-on-write between particles.
//!
//! Cloning a [`Grid`] copies only the tile index (one reference count per tile): a resampled
//! particle shares every tile with its parent. A write into a shared tile goes into a small delta
//! over it (the changed cells only: cell-level copy-on-write); a delta that grows past
//! [`DELTA_MAX`] cells becomes a tile of its own, and one whose base nobody else holds any more is
//! folded into it in place. After a filter update, [`share_written_tiles`] turns the tiles the
//! particles wrote alike (siblings writing one scan from nearly the same pose) into deltas over
//! one another's. Cells keep, besides their log-odds, the mean of the beam end
//! points that hit them (as gmapping does), so scan matching is not limited to the cell's centre.
//!
//! Coordinates: the grid frame is the map (world) frame; cell (i, j) covers
//! `[i·res, (i+1)·res) × [j·res, (j+1)·res)` metres. Cell indices may be negative; the grid grows
//! in whole tiles on demand.

use std::sync::Arc;

/// Cells along a tile's side (a power of two).
pub const TILE_SIDE: usize = 16;
const TILE_BITS: i32 = 4;
const TILE_MASK: i32 = TILE_SIDE as i32 - 1;

/// One cell: log-odds of occupancy and the accumulated end points of the beams that hit it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Cell {
    /// ln(p / (1 − p)); 0 is unknown.
    pub log_odds: f32,
    /// Mean x offset of the hit end points from the cell's centre, m (kept as a mean, not a
    /// sum, so the matcher reads it without a division).
    pub mean_dx_m: f32,
    /// Mean y offset of the hit end points from the cell's centre, m.
    pub mean_dy_m: f32,
    /// Number of hits averaged.
    pub hits: u32,
}

/// A tile of `TILE_SIDE`² cells, row-major (y then x).
#[derive(Debug, Clone)]
pub struct Tile {
    cells: [Cell; TILE_SIDE * TILE_SIDE],
}

impl Default for Tile {
    fn default() -> Self {
        Self { cells: [Cell::default(); TILE_SIDE * TILE_SIDE] }
    }
}

/// Log-odds update parameters.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogOddsParams {
    /// Added to a cell a beam ends in (ln(0.7/0.3) for P(hit) = 0.7).
    pub hit: f32,
    /// Added to a cell a beam passes through (ln(0.4/0.6) for P(miss) = 0.4).
    pub miss: f32,
    /// Lower clamp (ln(0.1192/0.8808)).
    pub min: f32,
    /// Upper clamp (ln(0.971/0.029)).
    pub max: f32,
}

impl Default for LogOddsParams {
    fn default() -> Self {
        Self { hit: 0.847_298, miss: -0.405_465, min: -2.0, max: 3.5 }
    }
}

/// Changed cells a delta holds before it becomes a full tile of its own.
pub const DELTA_MAX: usize = 48;

/// A tile's changes over a shared base tile: cell k is `cells[pos[k] - 1]` where `pos[k] > 0`,
/// else the base's.
#[derive(Debug, Clone)]
pub struct DeltaTile {
    base: Arc<Tile>,
    pos: [u8; TILE_SIDE * TILE_SIDE],
    cells: Vec<Cell>,
}

impl DeltaTile {
    fn new(base: Arc<Tile>) -> Self {
        Self { base, pos: [0; TILE_SIDE * TILE_SIDE], cells: Vec::new() }
    }

    #[inline(always)]
    fn has(&self, k: usize) -> bool {
        self.pos[k] != 0
    }

    #[inline(always)]
    fn get(&self, k: usize) -> &Cell {
        match self.pos[k] {
            0 => &self.base.cells[k],
            p => &self.cells[p as usize - 1],
        }
    }

    /// The cell for writing, copied from the base first if it is not in the delta yet.
    #[inline]
    fn get_mut(&mut self, k: usize) -> &mut Cell {
        if self.pos[k] == 0 {
            self.cells.push(self.base.cells[k]);
            self.pos[k] = self.cells.len() as u8;
        }
        &mut self.cells[self.pos[k] as usize - 1]
    }

    /// `tile` as a delta over `base`, if they differ in at most `max_cells` cells.
    fn between(base: &Arc<Tile>, tile: &Tile, max_cells: usize) -> Option<Self> {
        let mut d = Self::new(base.clone());
        for (k, (a, b)) in base.cells.iter().zip(&tile.cells).enumerate() {
            if a != b {
                if d.cells.len() >= max_cells {
                    return None;
                }
                d.cells.push(*b);
                d.pos[k] = d.cells.len() as u8;
            }
        }
        d.cells.shrink_to_fit();
        Some(d)
    }

    fn materialise(&self) -> Tile {
        let mut t = (*self.base).clone();
        for (k, c) in t.cells.iter_mut().enumerate() {
            *c = *self.get(k);
        }
        t
    }

    fn bytes(&self) -> usize {
        std::mem::size_of::<DeltaTile>() + self.cells.capacity() * std::mem::size_of::<Cell>()
    }
}

/// Read access to one tile's cells ([`Grid::tile_around`]).
#[derive(Debug, Clone, Copy)]
pub enum TileRef<'a> {
    /// Nothing written there.
    Empty,
    /// A tile.
    Full(&'a Tile),
    /// A delta over a shared tile.
    Delta(&'a DeltaTile),
}

impl TileRef<'_> {
    /// Cell (i, j), which must lie in this tile (`None` where nothing was written).
    #[inline(always)]
    pub fn cell(&self, i: i32, j: i32) -> Option<&Cell> {
        let k = ((j & TILE_MASK) as usize) * TILE_SIDE + (i & TILE_MASK) as usize;
        match self {
            TileRef::Empty => None,
            TileRef::Full(t) => Some(&t.cells[k]),
            TileRef::Delta(d) => Some(d.get(k)),
        }
    }
}

/// ⌊v⌋ as an i32 without a libm call (the default x86-64 target has no rounding instruction);
/// values beyond the i32 range saturate, like `floor() as i32`.
#[inline(always)]
fn floor_i32(v: f64) -> i32 {
    let t = v as i32;
    if (t as f64) > v { t.saturating_sub(1) } else { t }
}

/// A tile slot: nothing, a tile, or a delta over a shared tile.
#[derive(Debug, Clone, Default)]
enum Slot {
    #[default]
    Empty,
    Full(Arc<Tile>),
    Delta(Arc<DeltaTile>),
}

/// One tile as plain data: (tile x, tile y, cells row-major as (log-odds, mean hit dx, mean hit
/// dy, hits)).
pub type TileData = (i32, i32, Vec<(f32, f32, f32, u32)>);

/// The occupancy grid of one particle.
#[derive(Debug, Clone)]
pub struct Grid {
    resolution_m: f64,
    /// 1 / `resolution_m`.
    inv_resolution: f64,
    /// Tile index range: tiles `[tx0, tx0 + nx) × [ty0, ty0 + ny)`.
    tx0: i32,
    ty0: i32,
    nx: i32,
    ny: i32,
    tiles: Vec<Slot>,
    /// Per slot: the write generation it was last written in (parallel to `tiles`).
    written: Vec<u32>,
    /// The current write generation (bumped by [`Grid::take_written`]).
    generation: u32,
    /// Tiles (absolute tile coordinates) written in the current generation.
    dirty: Vec<(i32, i32)>,
}

impl Grid {
    /// An empty grid with square cells of `resolution_m`.
    pub fn new(resolution_m: f64) -> Self {
        Self {
            resolution_m,
            inv_resolution: 1.0 / resolution_m,
            tx0: 0,
            ty0: 0,
            nx: 0,
            ny: 0,
            tiles: Vec::new(),
            written: Vec::new(),
            generation: 1,
            dirty: Vec::new(),
        }
    }

    /// Cell side, m.
    pub fn resolution_m(&self) -> f64 {
        self.resolution_m
    }

    /// The cell containing world point (x, y).
    #[inline]
    pub fn cell_of(&self, x_m: f64, y_m: f64) -> (i32, i32) {
        (floor_i32(x_m * self.inv_resolution), floor_i32(y_m * self.inv_resolution))
    }

    /// The centre of cell (i, j), m.
    #[inline]
    pub fn centre_of(&self, i: i32, j: i32) -> (f64, f64) {
        ((i as f64 + 0.5) * self.resolution_m, (j as f64 + 0.5) * self.resolution_m)
    }

    /// The cell (i, j), or `None` where nothing was ever written.
    #[inline(always)]
    pub fn cell(&self, i: i32, j: i32) -> Option<&Cell> {
        let (tx, ty) = ((i >> TILE_BITS) - self.tx0, (j >> TILE_BITS) - self.ty0);
        if tx < 0 || ty < 0 || tx >= self.nx || ty >= self.ny {
            return None;
        }
        let k = ((j & TILE_MASK) as usize) * TILE_SIDE + (i & TILE_MASK) as usize;
        match &self.tiles[(ty * self.nx + tx) as usize] {
            Slot::Empty => None,
            Slot::Full(t) => Some(&t.cells[k]),
            Slot::Delta(d) => Some(d.get(k)),
        }
    }

    /// Log-odds of cell (i, j) (0 where unknown).
    #[inline]
    pub fn log_odds(&self, i: i32, j: i32) -> f32 {
        self.cell(i, j).map_or(0.0, |c| c.log_odds)
    }

    /// The mean hit point of cell (i, j) if it is occupied (log-odds above `threshold`).
    #[inline]
    pub fn occupied_mean(&self, i: i32, j: i32, threshold: f32) -> Option<(f64, f64)> {
        self.mean_of(self.cell(i, j)?, i, j, threshold)
    }

    /// The tile holding every cell of the window (i0..=i1, j0..=j1), `None` if the window spans
    /// more than one tile (`TileRef::Empty` where nothing was written there).
    #[inline(always)]
    pub fn tile_holding(&self, (i0, j0): (i32, i32), (i1, j1): (i32, i32)) -> Option<TileRef<'_>> {
        let (tx, ty) = (i0 >> TILE_BITS, j0 >> TILE_BITS);
        if i1 >> TILE_BITS != tx || j1 >> TILE_BITS != ty {
            return None;
        }
        self.tile_around(i0, j0, 0)
    }

    /// The tile holding cell (i, j), when every cell within `margin` cells of it lies in that
    /// tile too: lookups around (i, j) then skip the tile search (the matcher's fast path).
    #[inline(always)]
    pub fn tile_around(&self, i: i32, j: i32, margin: i32) -> Option<TileRef<'_>> {
        let (li, lj) = (i & TILE_MASK, j & TILE_MASK);
        if li < margin || lj < margin || li > TILE_MASK - margin || lj > TILE_MASK - margin {
            return None;
        }
        let (tx, ty) = ((i >> TILE_BITS) - self.tx0, (j >> TILE_BITS) - self.ty0);
        if tx < 0 || ty < 0 || tx >= self.nx || ty >= self.ny {
            return Some(TileRef::Empty);
        }
        Some(match &self.tiles[(ty * self.nx + tx) as usize] {
            Slot::Empty => TileRef::Empty,
            Slot::Full(t) => TileRef::Full(t),
            Slot::Delta(d) => TileRef::Delta(d),
        })
    }

    /// The mean hit point of cell `c` (at (i, j)) if it is occupied (log-odds above `threshold`).
    #[inline(always)]
    pub fn mean_of(&self, c: &Cell, i: i32, j: i32, threshold: f32) -> Option<(f64, f64)> {
        if c.log_odds <= threshold {
            return None;
        }
        let (cx, cy) = self.centre_of(i, j);
        Some((cx + c.mean_dx_m as f64, cy + c.mean_dy_m as f64))
    }

    fn grow_to(&mut self, tx: i32, ty: i32) {
        if self.nx > 0 && tx >= self.tx0 && ty >= self.ty0 && tx < self.tx0 + self.nx && ty < self.ty0 + self.ny {
            return;
        }
        // Grow with a margin so a moving robot does not regrow at every scan.
        const MARGIN: i32 = 4;
        let (x0, y0, x1, y1) = if self.nx == 0 {
            (tx - MARGIN, ty - MARGIN, tx + MARGIN + 1, ty + MARGIN + 1)
        } else {
            let x0 = if tx < self.tx0 { tx - MARGIN } else { self.tx0 };
            let y0 = if ty < self.ty0 { ty - MARGIN } else { self.ty0 };
            let x1 = if tx >= self.tx0 + self.nx { tx + MARGIN + 1 } else { self.tx0 + self.nx };
            let y1 = if ty >= self.ty0 + self.ny { ty + MARGIN + 1 } else { self.ty0 + self.ny };
            (x0, y0, x1, y1)
        };
        let (nx, ny) = (x1 - x0, y1 - y0);
        let mut tiles = vec![Slot::Empty; (nx * ny) as usize];
        let mut written = vec![0; (nx * ny) as usize];
        for y in 0..self.ny {
            for x in 0..self.nx {
                let src = (y * self.nx + x) as usize;
                let dst = ((y + self.ty0 - y0) * nx + (x + self.tx0 - x0)) as usize;
                tiles[dst] = std::mem::take(&mut self.tiles[src]);
                written[dst] = self.written[src];
            }
        }
        (self.tx0, self.ty0, self.nx, self.ny, self.tiles, self.written) = (x0, y0, nx, ny, tiles, written);
    }

    /// The cell (i, j) for writing: grows the grid and creates the tile. A tile another grid
    /// shares is not copied: the write goes into a delta over it (cell-level copy-on-write),
    /// which becomes a tile of its own once it holds [`DELTA_MAX`] cells.
    #[inline]
    pub fn cell_mut(&mut self, i: i32, j: i32) -> &mut Cell {
        let (tx, ty) = (i >> TILE_BITS, j >> TILE_BITS);
        self.grow_to(tx, ty);
        let slot = ((ty - self.ty0) * self.nx + (tx - self.tx0)) as usize;
        let k = ((j & TILE_MASK) as usize) * TILE_SIDE + (i & TILE_MASK) as usize;
        if self.written[slot] != self.generation {
            self.written[slot] = self.generation;
            self.dirty.push((tx, ty));
        }
        let s = &mut self.tiles[slot];
        match s {
            Slot::Empty => *s = Slot::Full(Arc::new(Tile::default())),
            Slot::Full(t) if Arc::strong_count(t) > 1 || Arc::weak_count(t) > 0 => {
                let base = t.clone();
                *s = Slot::Delta(Arc::new(DeltaTile::new(base)));
            }
            Slot::Delta(d) if Arc::strong_count(d) == 1 && Arc::strong_count(&d.base) == 1 => {
                // Nobody else holds the base any more: fold the delta into it, in place.
                let Slot::Delta(d) = std::mem::take(s) else { unreachable!("matched above") };
                let (pos, cells, mut base) = match Arc::try_unwrap(d) {
                    Ok(d) => (d.pos, d.cells, d.base),
                    Err(_) => unreachable!("the count was 1"),
                };
                let t = Arc::make_mut(&mut base);
                for (c, p) in t.cells.iter_mut().zip(pos) {
                    if p != 0 {
                        *c = cells[p as usize - 1];
                    }
                }
                *s = Slot::Full(base);
            }
            Slot::Delta(d) if d.cells.len() >= DELTA_MAX && !d.has(k) => {
                *s = Slot::Full(Arc::new(d.materialise()));
            }
            _ => {}
        }
        match s {
            Slot::Full(t) => &mut Arc::make_mut(t).cells[k],
            Slot::Delta(d) => Arc::make_mut(d).get_mut(k),
            Slot::Empty => unreachable!("filled above"),
        }
    }

    /// A miss: the beam passed through cell (i, j). A miss on a cell already at the lower clamp
    /// changes nothing and writes nothing, so it does not copy a shared tile (most of a scan's
    /// misses fall in free space seen many times before).
    #[inline]
    pub fn add_miss(&mut self, i: i32, j: i32, p: &LogOddsParams) {
        if self.cell(i, j).is_some_and(|c| c.log_odds <= p.min) {
            return;
        }
        let c = self.cell_mut(i, j);
        c.log_odds = (c.log_odds + p.miss).clamp(p.min, p.max);
    }

    /// A hit: a beam ended at world point (x, y).
    #[inline]
    pub fn add_hit(&mut self, x_m: f64, y_m: f64, p: &LogOddsParams) {
        let (i, j) = self.cell_of(x_m, y_m);
        let (cx, cy) = self.centre_of(i, j);
        let c = self.cell_mut(i, j);
        c.log_odds = (c.log_odds + p.hit).clamp(p.min, p.max);
        if c.hits < u32::MAX {
            c.hits += 1;
            let w = 1.0 / c.hits as f32;
            c.mean_dx_m += ((x_m - cx) as f32 - c.mean_dx_m) * w;
            c.mean_dy_m += ((y_m - cy) as f32 - c.mean_dy_m) * w;
        }
    }

    /// Casts one beam from `from` to `to` (world, m): misses on the cells strictly before the end
    /// cell, and a hit at `to` when `hit` is set (a beam cut at the usable range updates free space
    /// only).
    pub fn cast(&mut self, from: (f64, f64), to: (f64, f64), hit: bool, p: &LogOddsParams) {
        let (i0, j0) = self.cell_of(from.0, from.1);
        let (i1, j1) = self.cell_of(to.0, to.1);
        // Bresenham over the cells from (i0, j0) up to, not including, (i1, j1).
        let (dx, dy) = ((i1 - i0).abs(), -(j1 - j0).abs());
        let (sx, sy) = (if i0 < i1 { 1 } else { -1 }, if j0 < j1 { 1 } else { -1 });
        let (mut i, mut j, mut err) = (i0, j0, dx + dy);
        while (i, j) != (i1, j1) {
            self.add_miss(i, j, p);
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                i += sx;
            }
            if e2 <= dx {
                err += dx;
                j += sy;
            }
        }
        if hit {
            self.add_hit(to.0, to.1, p);
        }
    }

    /// Bytes of the tiles and deltas this grid holds that are not in `seen` yet (pointers),
    /// adding them: called over several grids, the memory they hold between them.
    pub fn add_bytes(&self, seen: &mut std::collections::HashSet<usize>) -> usize {
        let mut bytes = 0;
        for s in &self.tiles {
            match s {
                Slot::Empty => {}
                Slot::Full(t) => {
                    if seen.insert(Arc::as_ptr(t) as usize) {
                        bytes += Self::TILE_BYTES;
                    }
                }
                Slot::Delta(d) => {
                    if seen.insert(Arc::as_ptr(d) as usize) {
                        bytes += d.bytes();
                    }
                    if seen.insert(Arc::as_ptr(&d.base) as usize) {
                        bytes += Self::TILE_BYTES;
                    }
                }
            }
        }
        bytes
    }

    /// The tiles (absolute tile coordinates) written since the last call, and starts a new
    /// write generation.
    pub fn take_written(&mut self) -> Vec<(i32, i32)> {
        self.generation = self.generation.wrapping_add(1).max(1);
        std::mem::take(&mut self.dirty)
    }

    fn slot_index(&self, tx: i32, ty: i32) -> Option<usize> {
        let (x, y) = (tx - self.tx0, ty - self.ty0);
        (x >= 0 && y >= 0 && x < self.nx && y < self.ny).then(|| (y * self.nx + x) as usize)
    }

    /// Bytes of this grid alone (its tiles, deltas and their bases).
    pub fn bytes(&self) -> usize {
        self.add_bytes(&mut std::collections::HashSet::new())
    }

    /// The tiles this grid holds (full tiles and delta bases), as pointers.
    pub fn tile_ptrs(&self) -> impl Iterator<Item = *const Tile> + '_ {
        self.tiles.iter().filter_map(|s| match s {
            Slot::Empty => None,
            Slot::Full(t) => Some(Arc::as_ptr(t)),
            Slot::Delta(d) => Some(Arc::as_ptr(&d.base)),
        })
    }

    /// Number of tiles (full or delta) allocated.
    pub fn tile_count(&self) -> usize {
        self.tiles.iter().filter(|s| !matches!(s, Slot::Empty)).count()
    }

    /// The cells of slot `s` (copied), or `None` if empty.
    fn slot_cells(s: &Slot) -> Option<std::borrow::Cow<'_, Tile>> {
        match s {
            Slot::Empty => None,
            Slot::Full(t) => Some(std::borrow::Cow::Borrowed(&**t)),
            Slot::Delta(d) => Some(std::borrow::Cow::Owned(d.materialise())),
        }
    }

    /// Bytes of one tile.
    pub const TILE_BYTES: usize = std::mem::size_of::<Tile>();

    /// The tiles as plain data: (tile x, tile y, cells row-major as (log-odds, mean hit dx,
    /// mean hit dy, hits)), for a snapshot.
    pub fn to_tiles(&self) -> Vec<TileData> {
        let mut out = Vec::new();
        for ty in 0..self.ny {
            for tx in 0..self.nx {
                if let Some(t) = Self::slot_cells(&self.tiles[(ty * self.nx + tx) as usize]) {
                    let cells = t.cells.iter().map(|c| (c.log_odds, c.mean_dx_m, c.mean_dy_m, c.hits)).collect();
                    out.push((tx + self.tx0, ty + self.ty0, cells));
                }
            }
        }
        out
    }

    /// A grid from [`Grid::to_tiles`]' data; `None` if a tile has the wrong cell count.
    pub fn from_tiles(resolution_m: f64, tiles: &[TileData]) -> Option<Self> {
        let mut g = Grid::new(resolution_m);
        for (tx, ty, cells) in tiles {
            if cells.len() != TILE_SIDE * TILE_SIDE {
                return None;
            }
            let mut tile = Tile::default();
            for (c, &(l, dx, dy, n)) in tile.cells.iter_mut().zip(cells) {
                *c = Cell { log_odds: l, mean_dx_m: dx, mean_dy_m: dy, hits: n };
            }
            g.grow_to(*tx, *ty);
            let k = ((ty - g.ty0) * g.nx + (tx - g.tx0)) as usize;
            g.tiles[k] = Slot::Full(Arc::new(tile));
        }
        Some(g)
    }

    /// The bounds of the known cells: (i_min, j_min, i_max, j_max), inclusive; `None` if empty.
    pub fn known_bounds(&self) -> Option<(i32, i32, i32, i32)> {
        let mut b: Option<(i32, i32, i32, i32)> = None;
        for ty in 0..self.ny {
            for tx in 0..self.nx {
                let Some(tile) = Self::slot_cells(&self.tiles[(ty * self.nx + tx) as usize]) else { continue };
                for (k, c) in tile.cells.iter().enumerate() {
                    if c.log_odds == 0.0 {
                        continue;
                    }
                    let i = ((tx + self.tx0) << TILE_BITS) + (k % TILE_SIDE) as i32;
                    let j = ((ty + self.ty0) << TILE_BITS) + (k / TILE_SIDE) as i32;
                    b = Some(match b {
                        None => (i, j, i, j),
                        Some((a, bb, c2, d)) => (a.min(i), bb.min(j), c2.max(i), d.max(j)),
                    });
                }
            }
        }
        b
    }
}

/// Shares the tiles the grids wrote since their last [`Grid::take_written`] between them (and
/// starts a new write generation in each): a written tile that differs from another grid's tile
/// at the same place in at most `max_cells` cells becomes a delta over that tile. Particles
/// descended from one parent write nearly the same cells with nearly the same poses (their
/// tiles differ mostly at the scan's end points), so after an update most of their newly written
/// tiles become small deltas over a sibling's instead of private copies. Returns the number of
/// tiles turned into deltas. Reading and writing a grid give the same values before and after.
pub fn share_written_tiles<'a>(grids: impl IntoIterator<Item = &'a mut Grid>, max_cells: usize) -> usize {
    /// Tiles kept per place to compare against.
    const REPS: usize = 6;
    let max_cells = max_cells.min(DELTA_LIMIT);
    let mut reps: std::collections::HashMap<(i32, i32), Vec<Arc<Tile>>> = std::collections::HashMap::new();
    // What each tile already processed became (clones of one particle hold the same tile).
    let mut done: std::collections::HashMap<usize, Slot> = std::collections::HashMap::new();
    let mut shared = 0;
    for g in grids {
        for (tx, ty) in g.take_written() {
            let Some(slot) = g.slot_index(tx, ty) else { continue };
            let Slot::Full(t) = &g.tiles[slot] else { continue };
            let key = Arc::as_ptr(t) as usize;
            if let Some(s) = done.get(&key) {
                g.tiles[slot] = s.clone();
                continue;
            }
            let t = t.clone();
            let candidates = reps.entry((tx, ty)).or_default();
            let mut result = Slot::Full(t.clone());
            for r in candidates.iter() {
                if Arc::ptr_eq(r, &t) {
                    break;
                }
                if let Some(d) = DeltaTile::between(r, &t, max_cells) {
                    result = if d.cells.is_empty() { Slot::Full(r.clone()) } else { Slot::Delta(Arc::new(d)) };
                    shared += 1;
                    break;
                }
            }
            if matches!(result, Slot::Full(_))
                && candidates.len() < REPS
                && !candidates.iter().any(|r| Arc::ptr_eq(r, &t))
            {
                candidates.push(t.clone());
            }
            g.tiles[slot] = result.clone();
            done.insert(key, result);
        }
    }
    shared
}

/// Most cells a delta may hold (its `pos` entries are `u8`).
const DELTA_LIMIT: usize = 255;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_clone_shares_every_tile_until_one_side_writes_and_then_copies_only_that_tile() {
        let p = LogOddsParams::default();
        let mut a = Grid::new(0.05);
        a.cast((0.0, 0.0), (5.0, 0.0), true, &p);
        a.cast((0.0, 0.0), (0.0, 5.0), true, &p);
        let tiles = a.tile_count();
        assert!(tiles >= 7, "{tiles}");
        let mut b = a.clone();
        let shared = |a: &Grid, b: &Grid| {
            let pa: std::collections::HashSet<_> = a.tile_ptrs().collect();
            b.tile_ptrs().filter(|t| pa.contains(t)).count()
        };
        assert_eq!(shared(&a, &b), tiles);
        b.add_miss(5, 0, &p);
        assert_eq!(shared(&a, &b), tiles, "a write into a shared tile goes into a delta over it");
        assert_eq!(a.log_odds(5, 0), p.miss, "the original is untouched");
        assert_eq!(b.log_odds(5, 0), (2.0 * p.miss).clamp(p.min, p.max));
        assert_eq!(b.log_odds(6, 0), a.log_odds(6, 0), "the other cells read through to the shared tile");
        let one = a.bytes();
        let mut seen = std::collections::HashSet::new();
        let both = a.add_bytes(&mut seen) + b.add_bytes(&mut seen);
        assert!(both < one + Grid::TILE_BYTES, "the delta costs less than a tile: {both} vs {one}");
        // Many writes into one shared tile make it a tile of its own, with every cell right.
        for i in 0..TILE_SIDE as i32 {
            for j in 0..4 {
                b.add_miss(i, j, &p);
            }
        }
        assert_eq!(shared(&a, &b), tiles - 1, "one tile copied");
        assert_eq!(b.log_odds(5, 0), (3.0 * p.miss).clamp(p.min, p.max));
        assert_eq!(b.log_odds(6, 5), a.log_odds(6, 5));
        assert_eq!(a.log_odds(5, 0), p.miss);
    }

    #[test]
    fn a_beam_frees_the_cells_before_its_end_and_marks_the_end_with_the_mean_hit_point() {
        let p = LogOddsParams::default();
        let mut g = Grid::new(0.1);
        g.cast((0.05, 0.05), (1.03, 0.05), true, &p);
        for i in 0..10 {
            assert!(g.log_odds(i, 0) < 0.0, "cell {i} free");
        }
        let (mx, my) = g.occupied_mean(10, 0, 0.0).expect("end cell occupied");
        assert!((mx - 1.03).abs() < 1e-6 && (my - 0.05).abs() < 1e-6);
        assert_eq!(g.log_odds(11, 0), 0.0);
        // Negative coordinates work the same, across tile borders.
        g.cast((0.0, 0.0), (-4.0, -3.0), false, &p);
        assert!(g.log_odds(-20, -15) < 0.0);
        assert_eq!(g.known_bounds().map(|b| b.0), Some(-39), "the end cell of a beam without a hit is not touched");
    }

    #[test]
    fn tiles_written_alike_are_shared_as_deltas_and_every_cell_reads_the_same() {
        let p = LogOddsParams::default();
        let mut parent = Grid::new(0.05);
        let fan = |g: &mut Grid, ox: f64, oy: f64, dtheta: f64| {
            for b in 0..180 {
                let a = (b as f64).to_radians() * 2.0 + dtheta;
                g.cast((ox, oy), (ox + 4.0 * a.cos(), oy + 3.0 * a.sin()), true, &p);
            }
        };
        fan(&mut parent, 0.0, 0.0, 0.0);
        parent.take_written();
        // Four children of one parent write the next scan from slightly different poses; two of
        // them are clones (a resampled particle picked twice).
        let mut kids: Vec<Grid> = (0..3).map(|_| parent.clone()).collect();
        for (k, g) in kids.iter_mut().enumerate() {
            fan(g, 0.5 + 0.002 * k as f64, 0.1, 0.001 * k as f64);
        }
        kids.push(kids[2].clone());
        let before: Vec<Vec<TileData>> = kids.iter().map(Grid::to_tiles).collect();
        let bytes = |gs: &[Grid]| {
            let mut seen = std::collections::HashSet::new();
            gs.iter().map(|g| g.add_bytes(&mut seen)).sum::<usize>()
        };
        let (held, one) = (bytes(&kids), kids[0].bytes());
        let shared = share_written_tiles(kids.iter_mut(), 128);
        assert!(shared > 10, "{shared} tiles shared");
        let after: Vec<Vec<TileData>> = kids.iter().map(Grid::to_tiles).collect();
        assert_eq!(before, after, "every cell of every grid reads as before");
        let held_after = bytes(&kids);
        assert!(held_after < held * 3 / 4, "{held} -> {held_after} bytes (one grid: {one})");
        assert!(kids.iter().all(|g| g.dirty.is_empty()), "a new write generation");
        // Writing after sharing copies on write as before: the sibling is untouched.
        let (i, j) = kids[1].cell_of(0.55, 0.15);
        let was = kids[0].log_odds(i, j);
        assert_eq!(kids[2].log_odds(i, j), kids[1].log_odds(i, j), "this cell is alike in the two");
        for _ in 0..3 {
            kids[1].add_hit(0.55, 0.15, &p);
        }
        assert_eq!(kids[0].log_odds(i, j), was);
        let expected = (0..3).fold(kids[2].log_odds(i, j), |l, _| (l + p.hit).clamp(p.min, p.max));
        assert_eq!(kids[1].log_odds(i, j), expected);
        assert_eq!(kids[1].take_written().len(), 1, "the written tile is listed once");
        // Nothing written, nothing shared.
        assert_eq!(share_written_tiles(kids.iter_mut(), 128), 0);
    }

    #[test]
    fn log_odds_are_clamped() {
        let p = LogOddsParams::default();
        let mut g = Grid::new(0.05);
        for _ in 0..100 {
            g.add_hit(0.01, 0.01, &p);
            g.add_miss(5, 5, &p);
        }
        assert_eq!(g.log_odds(0, 0), p.max);
        assert_eq!(g.log_odds(5, 5), p.min);
    }
}
