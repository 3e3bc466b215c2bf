//! Paging: which tiles to hold around the viewpoint, which to request and which to drop.
//!
//! This is Algorithm 1 of the strip-mask paper ("asynchronous adaptive tiling", Pouderoux
//! and Marvie 2005, section 4) as one pure function, [`decide`], called once per frame. It
//! keeps the largest square of complete *belts* around the current tile that the memory
//! limit allows. Belt `k` is the ring of tiles at Chebyshev distance `k` from the current
//! tile ([`belt_of`]), clipped to the grid; belt 0 is the current tile itself.
//!
//! - Fetch by belts, nearest first, and start a belt only when nothing is in flight: the
//!   paper fetches "belt dc + 1" only "if the last requested belt has been completely
//!   fetched".
//! - Over the limit, drop the farthest belt holding any tile, and only when it lies beyond
//!   the farthest complete belt; a complete belt of the square is never dropped, which is
//!   what keeps the square stable (and why the limit is 90% of the budget: the belt being
//!   fetched may overspend it).
//! - Under the limit, tiles outside the square stay cached.
//! - A viewpoint off the terrain makes the nearest tile current (the paper's option, which
//!   can be turned off so that belts are counted from a virtual tile outside the grid).
//!   Near an edge the square becomes a rectangle; a jump to a far tile needs nothing special.
//!
//! The module owns these rules and nothing else. The caller (`flight`) owns fetching,
//! decoding and counting each tile's bytes, the limit's percentage (`memory`), and carrying
//! a [`Decision`] out: cancel, evict, request, then report the new state on the next frame.
//! Nothing here does IO, reads a clock or awaits; [`decide`] allocates only the vectors it
//! returns and makes one pass over the grid (benches/pager.rs: a few microseconds for
//! 64x64 tiles), so it can run every frame.

use std::fmt;
use terrain_shared::TileId;

/// Configuration that does not change from frame to frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PagerConfig {
    /// Tile grid columns, as in the manifest's `grid`.
    pub columns: u32,
    /// Tile grid rows, as in the manifest's `grid`.
    pub rows: u32,
    /// Bytes the resident tiles may fill: already the percentage of the budget (the caller
    /// applies the paper's 90%).
    pub memory_limit: u64,
    /// Make the tile nearest to a viewpoint off the terrain current (the paper's option,
    /// on by default). Off, the belts are counted from a virtual tile outside the grid, as
    /// for terrains placed side by side.
    pub nearest_when_outside: bool,
}

impl PagerConfig {
    /// A grid and a limit, with the nearest tile current when the viewpoint is off the terrain.
    pub const fn new(columns: u32, rows: u32, memory_limit: u64) -> PagerConfig {
        PagerConfig {
            columns,
            rows,
            memory_limit,
            nearest_when_outside: true,
        }
    }

    /// Tiles in the grid: the length of every per-tile slice of a [`PagerView`].
    pub fn tile_count(&self) -> usize {
        self.columns as usize * self.rows as usize
    }

    /// Position of `id` in the row-major per-tile slices (`y * columns + x`).
    pub fn index(&self, id: TileId) -> usize {
        id.y as usize * self.columns as usize + id.x as usize
    }
}

/// What the pager sees each frame. The slices are dense and row-major (`y * columns + x`),
/// one entry per tile, so a decision is a scan rather than a hash lookup per tile.
#[derive(Debug, Clone, Copy)]
pub struct PagerView<'a> {
    /// Viewpoint in tile units, x east and y south: tile `(i, j)` spans `[i, i+1) x [j, j+1)`.
    /// It may lie outside the grid, negative included.
    pub viewpoint: [f64; 2],
    /// Bytes each tile holds; 0 means not resident.
    pub resident_bytes: &'a [u64],
    /// Requested and not yet delivered (nor cancelled).
    pub in_flight: &'a [bool],
    /// Bytes each tile will hold once resident, when the caller knows them before fetching
    /// (the manifest lists every blob's size). With them, a belt is fetched only if it fits
    /// under the limit whole, so resident bytes stay under the limit except for the current
    /// tile alone (which is always fetched); without them, the paper's rule: a belt is
    /// fetched whenever used bytes are under the limit, and may overspend by that belt.
    pub expected_bytes: Option<&'a [u64]>,
}

/// The tile the belts are counted from: a grid tile, or with
/// [`PagerConfig::nearest_when_outside`] off, possibly a virtual tile outside the grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct CurrentTile {
    pub x: i64,
    pub y: i64,
}

impl CurrentTile {
    /// The grid tile, when the current tile is inside the grid.
    pub fn tile(self, config: &PagerConfig) -> Option<TileId> {
        let x = u32::try_from(self.x).ok().filter(|&x| x < config.columns)?;
        let y = u32::try_from(self.y).ok().filter(|&y| y < config.rows)?;
        Some(TileId::new(x, y))
    }
}

impl fmt::Display for CurrentTile {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.x, self.y)
    }
}

/// What to do this frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Decision {
    /// The tile the belts are counted from.
    pub current: CurrentTile,
    /// Belts `0..complete_belts` around `current` are complete: every tile of them that lies
    /// in the grid is resident. A belt with no tile in the grid (around a virtual tile)
    /// counts as complete.
    pub complete_belts: u32,
    /// The paper's `dc`: `complete_belts - 1`, `None` while belt 0 is incomplete.
    pub farthest_complete_belt: Option<u32>,
    /// Belts `0..belt_count` around `current` cover the whole grid; when `complete_belts`
    /// reaches it, every tile is resident and nothing is left to fetch.
    pub belt_count: u32,
    /// Tiles of the belt being built are still in flight (after `cancel`), so nothing was
    /// fetched or evicted: the paper's "currently loading".
    pub loading: bool,
    /// Tiles to request now, nearest to the viewpoint first: the missing tiles of belt
    /// `complete_belts`.
    pub fetch: Vec<TileId>,
    /// Tiles to drop now: every resident tile of one belt beyond the square.
    pub evict: Vec<TileId>,
    /// In-flight tiles no longer wanted: those outside the belt being built.
    pub cancel: Vec<TileId>,
    /// Bytes resident when the decision was taken (before `evict`).
    pub used_bytes: u64,
}

/// Algorithm 1 for one frame: from the viewpoint and the state of every tile, what to fetch,
/// evict and cancel.
///
/// 1. In-flight tiles more than one belt beyond belt `complete_belts` (the belt being built
///    around the current tile) go in `cancel`, so a jump does not wait for the old belt. The
///    belt after the one being built is kept: a one-tile step moves tiles of the old belt
///    there, and they are wanted next (cancelling them cost 5% of all fetches, 779 of
///    15,500, in the pager bench's flight).
/// 2. If in-flight tiles remain, the pager is loading: nothing else happens.
/// 3. Else, over the limit: the farthest belt holding a resident tile is evicted whole if it
///    lies beyond the farthest complete belt; complete belts stay, even over the limit.
/// 4. Else, at or under the limit: the missing tiles of belt `complete_belts` are fetched,
///    nearest first, unless every belt is complete.
///
/// Step 2 looks at what remains after `cancel`, not at `view.in_flight`, so a jump starts its
/// new square in the same frame; the caller must carry `cancel` out before `fetch`.
///
/// # Panics
///
/// When `view.resident_bytes` or `view.in_flight` does not hold one entry per tile.
#[must_use]
pub fn decide(config: &PagerConfig, view: &PagerView<'_>) -> Decision {
    let tiles = config.tile_count();
    assert_eq!(
        view.resident_bytes.len(),
        tiles,
        "resident_bytes needs one entry per tile, row-major"
    );
    assert_eq!(
        view.in_flight.len(),
        tiles,
        "in_flight needs one entry per tile, row-major"
    );
    if let Some(expected) = view.expected_bytes {
        assert_eq!(
            expected.len(),
            tiles,
            "expected_bytes needs one entry per tile, row-major"
        );
    }
    let current = current_tile(config, view.viewpoint);
    let belt_count = belt_count(config, current);
    if tiles == 0 {
        // No tile, nothing to decide; the row scan below needs a column.
        return Decision {
            current,
            complete_belts: 0,
            farthest_complete_belt: None,
            belt_count,
            loading: false,
            fetch: Vec::new(),
            evict: Vec::new(),
            cancel: Vec::new(),
            used_bytes: 0,
        };
    }

    // One pass over the grid gathers what the algorithm needs: used bytes, the nearest belt
    // with a missing tile (every belt below it is complete) and the farthest belt with a
    // resident tile (the paper's dp). A tile's belt is the larger of its row's distance and
    // its column's, so within a row only two columns matter for each: the missing tile
    // nearest to the current column and the outermost resident tiles. Finding them stops
    // early, which makes the pass about as cheap as summing the bytes (benches/pager.rs).
    let mut used_bytes = 0u64;
    let mut complete_belts = belt_count;
    // Farthest belt holding a resident tile, plus one; 0 when nothing is resident.
    let mut resident_reach = 0u32;
    let columns = config.columns as usize;
    let nearest_column = current.x.clamp(0, i64::from(config.columns) - 1) as usize;
    for y in 0..config.rows {
        let row_belt = distance(current.y, y);
        let row = &view.resident_bytes[y as usize * columns..(y as usize + 1) * columns];
        let row_bytes: u64 = row.iter().sum();
        used_bytes += row_bytes;
        // The sum is vectorized; most rows of a large grid hold nothing and stop here.
        if row_bytes > 0
            && let Some(first) = row.iter().position(|&b| b > 0)
        {
            let last = row.iter().rposition(|&b| b > 0).unwrap_or(first);
            let column_belt =
                distance(current.x, first as u32).max(distance(current.x, last as u32));
            resident_reach = resident_reach.max(row_belt.max(column_belt).saturating_add(1));
        }
        // A row at or beyond the nearest incomplete belt found so far cannot lower it.
        if row_belt < complete_belts {
            let left = row[..=nearest_column].iter().rposition(|&b| b == 0);
            let right = row[nearest_column..]
                .iter()
                .position(|&b| b == 0)
                .map(|offset| nearest_column + offset);
            let column_belt = [left, right]
                .into_iter()
                .flatten()
                .map(|x| distance(current.x, x as u32))
                .min();
            if let Some(column_belt) = column_belt {
                complete_belts = complete_belts.min(row_belt.max(column_belt));
            }
        }
    }
    let farthest_resident_belt = resident_reach.checked_sub(1);

    // The tiles of the belt being built, and of the one after it, stay in flight; any other
    // in-flight tile belongs to a square the viewpoint has left. In-flight tiles are few (one belt at most), so the flags
    // are scanned a block at a time: an OR over a block is branch-free and cheap.
    let mut in_flight = 0;
    let mut cancel = Vec::new();
    for (block, flags) in view.in_flight.chunks(IN_FLIGHT_BLOCK).enumerate() {
        if !flags.iter().fold(false, |any, &flag| any | flag) {
            continue;
        }
        for (offset, _) in flags.iter().enumerate().filter(|&(_, &flag)| flag) {
            let i = block * IN_FLIGHT_BLOCK + offset;
            let id = TileId::new((i % columns) as u32, (i / columns) as u32);
            in_flight += 1;
            if belt_of(current, id) > complete_belts + 1 {
                cancel.push(id);
            }
        }
    }
    let loading = cancel.len() < in_flight;

    let mut decision = Decision {
        current,
        complete_belts,
        farthest_complete_belt: complete_belts.checked_sub(1),
        belt_count,
        loading,
        fetch: Vec::new(),
        evict: Vec::new(),
        cancel,
        used_bytes,
    };
    if loading {
        // The paper's "initialize each received tile" branch: the caller does that.
        return decision;
    }
    if used_bytes > config.memory_limit {
        // dp > dc, with dc = complete_belts - 1 (and -1 when belt 0 is incomplete).
        if let Some(farthest) = farthest_resident_belt
            && farthest >= complete_belts
        {
            decision.evict = belt_tiles(config, current, farthest)
                .filter(|&id| view.resident_bytes[config.index(id)] > 0)
                .collect();
        }
    } else if complete_belts < belt_count {
        let mut fetch: Vec<TileId> = belt_tiles(config, current, complete_belts)
            .filter(|&id| view.resident_bytes[config.index(id)] == 0)
            .collect();
        let [vx, vy] = view.viewpoint;
        let squared_distance = |id: &TileId| {
            let (dx, dy) = (f64::from(id.x) + 0.5 - vx, f64::from(id.y) + 0.5 - vy);
            dx * dx + dy * dy
        };
        // Ties (common: a belt is symmetric) go in row-major order, so a decision depends on
        // its inputs alone.
        fetch.sort_unstable_by(|a, b| {
            squared_distance(a)
                .total_cmp(&squared_distance(b))
                .then((a.y, a.x).cmp(&(b.y, b.x)))
        });
        // Predicted admission: a belt beyond the current tile starts only if all of it fits.
        // When it does not, the farthest belt beyond it (cached tiles the square does not
        // use) makes room, one belt a frame; when nothing is left to drop, the square has
        // reached the largest size that fits and stays.
        if let Some(expected) = view.expected_bytes
            && complete_belts > 0
        {
            let needed: u64 = fetch.iter().map(|&id| expected[config.index(id)]).sum();
            if used_bytes.saturating_add(needed) > config.memory_limit {
                if let Some(farthest) = farthest_resident_belt
                    && farthest > complete_belts
                {
                    decision.evict = belt_tiles(config, current, farthest)
                        .filter(|&id| view.resident_bytes[config.index(id)] > 0)
                        .collect();
                }
                return decision;
            }
        }
        decision.fetch = fetch;
    }
    decision
}

/// The current tile for a viewpoint: the tile under it, or with
/// [`PagerConfig::nearest_when_outside`] on, the grid tile nearest to it (clamping each
/// coordinate finds it, the tiles being an axis-aligned grid).
///
/// A viewpoint more than 2^30 tiles off the grid is taken as 2^30 tiles off, which keeps belt
/// indices (2^30 plus the grid's side at most) within `u32`; a NaN coordinate is taken as 0.
pub fn current_tile(config: &PagerConfig, viewpoint: [f64; 2]) -> CurrentTile {
    let axis = |position: f64, tiles: u32| -> i64 {
        let tile = if position.is_nan() {
            0.0
        } else {
            position
                .floor()
                .clamp(-FAR_OFF_GRID, f64::from(tiles) + FAR_OFF_GRID)
        };
        let tile = tile as i64;
        if config.nearest_when_outside && tiles > 0 {
            tile.clamp(0, i64::from(tiles) - 1)
        } else {
            tile
        }
    };
    CurrentTile {
        x: axis(viewpoint[0], config.columns),
        y: axis(viewpoint[1], config.rows),
    }
}

/// The belt index of `tile` around `current`: the Chebyshev distance in tiles.
pub fn belt_of(current: CurrentTile, tile: TileId) -> u32 {
    distance(current.x, tile.x).max(distance(current.y, tile.y))
}

/// The tiles of belt `belt` around `current` that lie in the grid, in row-major order.
pub fn belt_tiles(
    config: &PagerConfig,
    current: CurrentTile,
    belt: u32,
) -> impl Iterator<Item = TileId> + use<> {
    let (columns, rows) = (i64::from(config.columns), i64::from(config.rows));
    let k = i64::from(belt);
    let (x0, x1) = (current.x.saturating_sub(k), current.x.saturating_add(k));
    let (y0, y1) = (current.y.saturating_sub(k), current.y.saturating_add(k));
    (y0.max(0)..=y1.min(rows - 1)).flat_map(move |y| {
        // The top and bottom rows of the ring are whole; the rows between hold its two sides.
        let (start, end, step) = if y == y0 || y == y1 {
            (x0.max(0), x1.min(columns - 1), 1)
        } else {
            (x0, x1, (2 * k).max(1) as usize)
        };
        (start..=end)
            .step_by(step)
            .filter(move |&x| (0..columns).contains(&x))
            .map(move |x| TileId::new(x as u32, y as u32))
    })
}

/// The tiles of belts `0..belts` around `current` that lie in the grid, in row-major order:
/// the square (near an edge, the rectangle) of complete belts when `belts` is
/// [`Decision::complete_belts`].
pub fn square_tiles(
    config: &PagerConfig,
    current: CurrentTile,
    belts: u32,
) -> impl Iterator<Item = TileId> + use<> {
    let (columns, rows) = (i64::from(config.columns), i64::from(config.rows));
    // With no belt the reach is -1: every range below is empty.
    let reach = i64::from(belts) - 1;
    let (x0, x1) = (
        current.x.saturating_sub(reach).max(0),
        current.x.saturating_add(reach).min(columns - 1),
    );
    let (y0, y1) = (
        current.y.saturating_sub(reach).max(0),
        current.y.saturating_add(reach).min(rows - 1),
    );
    (y0..=y1).flat_map(move |y| (x0..=x1).map(move |x| TileId::new(x as u32, y as u32)))
}

/// In-flight flags OR-ed together before looking at any one of them; 64 bytes, a cache line.
const IN_FLIGHT_BLOCK: usize = 64;

/// How far off the grid a viewpoint is taken to be at most, in tiles; see [`current_tile`].
const FAR_OFF_GRID: f64 = (1u64 << 30) as f64;

/// Number of belts around `current` that reach every tile of the grid: one more than the
/// belt of the farthest tile. Belt indices are a max over the two axes, so the farthest tile
/// takes the farthest column and the farthest row.
fn belt_count(config: &PagerConfig, current: CurrentTile) -> u32 {
    if config.columns == 0 || config.rows == 0 {
        return 0;
    }
    let columns = distance(current.x, 0).max(distance(current.x, config.columns - 1));
    let rows = distance(current.y, 0).max(distance(current.y, config.rows - 1));
    columns.max(rows).saturating_add(1)
}

/// Distance in tiles along one axis, saturated to `u32` (reached only by a grid more than
/// 3 * 2^30 tiles wide, see [`current_tile`]).
fn distance(current: i64, tile: u32) -> u32 {
    current.abs_diff(i64::from(tile)).min(u64::from(u32::MAX)) as u32
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    // --- single decisions, drawn as pictures ---------------------------------------------

    /// Runs [`decide`] on a grid drawn as text and compares a summary of the decision.
    /// In the picture `.` is a missing tile, `~` a tile in flight and a digit a resident tile
    /// holding that many bytes.
    fn check(picture: &str, viewpoint: [f64; 2], memory_limit: u64, expect: &str) {
        check_with(picture, viewpoint, memory_limit, true, expect);
    }

    fn check_with(
        picture: &str,
        viewpoint: [f64; 2],
        memory_limit: u64,
        nearest_when_outside: bool,
        expect: &str,
    ) {
        let rows: Vec<&str> = picture
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .collect();
        let columns = rows.first().map_or(0, |r| r.len());
        assert!(
            rows.iter().all(|r| r.len() == columns),
            "ragged picture:\n{picture}"
        );
        let config = PagerConfig {
            nearest_when_outside,
            ..PagerConfig::new(columns as u32, rows.len() as u32, memory_limit)
        };
        let cells: Vec<char> = rows.iter().flat_map(|r| r.chars()).collect();
        let resident: Vec<u64> = cells
            .iter()
            .map(|c| c.to_digit(10).map_or(0, u64::from))
            .collect();
        let in_flight: Vec<bool> = cells.iter().map(|&c| c == '~').collect();
        let decision = decide(
            &config,
            &PagerView {
                viewpoint,
                resident_bytes: &resident,
                in_flight: &in_flight,
                expected_bytes: None,
            },
        );
        assert_eq!(summary(&decision), normalize(expect), "picture:\n{picture}");
    }

    fn summary(d: &Decision) -> String {
        let list = |ids: &[TileId]| {
            if ids.is_empty() {
                "-".to_string()
            } else {
                ids.iter()
                    .map(TileId::to_string)
                    .collect::<Vec<_>>()
                    .join(" ")
            }
        };
        format!(
            "current {} complete {} of {} used {}\nfetch {}\nevict {}\ncancel {}",
            d.current,
            d.complete_belts,
            d.belt_count,
            d.used_bytes,
            list(&d.fetch),
            list(&d.evict),
            list(&d.cancel)
        )
    }

    fn normalize(text: &str) -> String {
        text.lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .collect::<Vec<_>>()
            .join("\n")
    }

    #[test]
    fn fetch_order_is_nearest_first_with_ties_in_row_major_order() {
        check(
            "
            ...
            .1.
            ...
            ",
            [1.9, 1.5],
            100,
            "
            current 1/1 complete 1 of 2 used 1
            fetch 2/1 1/0 1/2 2/0 2/2 0/1 0/0 0/2
            evict -
            cancel -
            ",
        );
    }

    #[test]
    fn a_viewpoint_off_the_terrain_makes_the_nearest_tile_current() {
        check(
            "
            ....
            ....
            ....
            ",
            [-3.0, 1.5],
            100,
            "
            current 0/1 complete 0 of 4 used 0
            fetch 0/1
            evict -
            cancel -
            ",
        );
        // Past the far corner, on both axes.
        check(
            "
            ....
            ....
            ....
            ",
            [9.0, 40.0],
            100,
            "
            current 3/2 complete 0 of 4 used 0
            fetch 3/2
            evict -
            cancel -
            ",
        );
    }

    #[test]
    fn the_square_is_clipped_to_a_rectangle_at_an_edge() {
        // Current tile 0/0 (the nearest to the viewpoint): belt 1 is three tiles, belt 2 five.
        check(
            "
            11...
            11...
            .....
            .....
            ",
            [-2.0, 0.2],
            100,
            "
            current 0/0 complete 2 of 5 used 4
            fetch 0/2 1/2 2/0 2/1 2/2
            evict -
            cancel -
            ",
        );
    }

    #[test]
    fn with_the_option_off_belts_are_counted_from_a_virtual_tile_outside_the_grid() {
        // Virtual tile -3/1: belts 0 to 2 hold no tile and count as complete; belt 3 is column 0.
        check_with(
            "
            ....
            ....
            ....
            ....
            ",
            [-2.5, 1.5],
            100,
            false,
            "
            current -3/1 complete 3 of 7 used 0
            fetch 0/1 0/0 0/2 0/3
            evict -
            cancel -
            ",
        );
        check_with(
            "
            1...
            1...
            1...
            1...
            ",
            [-2.5, 1.5],
            100,
            false,
            "
            current -3/1 complete 4 of 7 used 4
            fetch 1/1 1/0 1/2 1/3
            evict -
            cancel -
            ",
        );
    }

    #[test]
    fn over_the_limit_the_farthest_partial_belt_beyond_the_square_is_evicted_one_belt_a_frame() {
        // Square: belts 0 and 1 around 3/3. Partial: 1/1 in belt 2, 0/0 and 6/3 in belt 3.
        check(
            "
            1......
            .1.....
            ..111..
            ..111.1
            ..111..
            .......
            .......
            ",
            [3.5, 3.5],
            5,
            "
            current 3/3 complete 2 of 4 used 12
            fetch -
            evict 0/0 6/3
            cancel -
            ",
        );
        check(
            "
            .......
            .1.....
            ..111..
            ..111..
            ..111..
            .......
            .......
            ",
            [3.5, 3.5],
            5,
            "
            current 3/3 complete 2 of 4 used 10
            fetch -
            evict 1/1
            cancel -
            ",
        );
    }

    #[test]
    fn over_the_limit_a_complete_belt_of_the_square_is_never_evicted() {
        check(
            "
            .......
            .......
            ..111..
            ..111..
            ..111..
            .......
            .......
            ",
            [3.5, 3.5],
            5,
            "
            current 3/3 complete 2 of 4 used 9
            fetch -
            evict -
            cancel -
            ",
        );
    }

    #[test]
    fn under_the_limit_partial_belts_stay_cached() {
        // Column 0 is belt 2 and resident; column 4, the rest of belt 2, is fetched.
        check(
            "
            1111.
            1111.
            1111.
            ",
            [2.5, 1.5],
            12,
            "
            current 2/1 complete 2 of 3 used 12
            fetch 4/1 4/0 4/2
            evict -
            cancel -
            ",
        );
        // One byte less and the same belt is dropped instead.
        check(
            "
            1111.
            1111.
            1111.
            ",
            [2.5, 1.5],
            11,
            "
            current 2/1 complete 2 of 3 used 12
            fetch -
            evict 0/0 0/1 0/2
            cancel -
            ",
        );
    }

    #[test]
    fn nothing_is_fetched_or_evicted_while_the_belt_being_built_is_in_flight() {
        check(
            "
            1111~
            1111.
            1111.
            ",
            [2.5, 1.5],
            11,
            "
            current 2/1 complete 2 of 3 used 12
            fetch -
            evict -
            cancel -
            ",
        );
    }

    #[test]
    fn a_jump_cancels_the_in_flight_tiles_of_the_old_belt_and_starts_the_new_square() {
        check(
            "
            111~..
            111~..
            111...
            ......
            ......
            ......
            ",
            [5.5, 5.5],
            100,
            "
            current 5/5 complete 0 of 6 used 9
            fetch 5/5
            evict -
            cancel 3/0 3/1
            ",
        );
        // A step to the next tile keeps what the new square still needs: around 2/2, 3/1 is
        // in belt 1, the belt being built, and 3/0 in belt 2, the next one: both stay.
        check(
            "
            111~..
            111~..
            111...
            ......
            ......
            ......
            ",
            [2.5, 2.5],
            100,
            "
            current 2/2 complete 1 of 4 used 9
            fetch -
            evict -
            cancel -
            ",
        );
    }

    #[test]
    fn belts_and_squares_are_clipped_to_the_grid() {
        let config = PagerConfig::new(5, 4, 0);
        let at = |x, y| CurrentTile { x, y };
        let ids = |tiles: &mut dyn Iterator<Item = TileId>| {
            tiles.map(|t| t.to_string()).collect::<Vec<_>>().join(" ")
        };
        assert_eq!(belt_of(at(-3, 1), TileId::new(0, 3)), 3);
        assert_eq!(belt_of(at(2, 2), TileId::new(4, 0)), 2);
        assert_eq!(ids(&mut belt_tiles(&config, at(0, 0), 0)), "0/0");
        assert_eq!(
            ids(&mut belt_tiles(&config, at(1, 1), 1)),
            "0/0 1/0 2/0 0/1 2/1 0/2 1/2 2/2"
        );
        assert_eq!(
            ids(&mut belt_tiles(&config, at(0, 0), 2)),
            "2/0 2/1 0/2 1/2 2/2"
        );
        assert_eq!(ids(&mut belt_tiles(&config, at(-3, 1), 2)), "");
        assert_eq!(ids(&mut belt_tiles(&config, at(9, 9), 3)), "");
        assert_eq!(ids(&mut square_tiles(&config, at(0, 0), 0)), "");
        assert_eq!(
            ids(&mut square_tiles(&config, at(0, 0), 2)),
            "0/0 1/0 0/1 1/1"
        );
        assert_eq!(ids(&mut square_tiles(&config, at(-1, 3), 2)), "0/2 0/3");
        assert_eq!(current_tile(&config, [f64::NAN, -1e300]), at(0, 0));
        assert_eq!(
            current_tile(
                &PagerConfig {
                    nearest_when_outside: false,
                    ..config
                },
                [7.2, -0.5]
            ),
            at(7, -1)
        );
        assert_eq!(at(4, 3).tile(&config), Some(TileId::new(4, 3)));
        assert_eq!(at(5, 3).tile(&config), None);
        let empty = PagerConfig::new(0, 3, 0);
        let view = PagerView {
            viewpoint: [1.0, 1.0],
            resident_bytes: &[],
            in_flight: &[],
            expected_bytes: None,
        };
        let decision = decide(&empty, &view);
        assert_eq!((decision.belt_count, decision.fetch.len()), (0, 0));
    }

    // --- many frames: a simulated fetcher ------------------------------------------------

    /// The caller's side of the pager, simulated: tiles land after a delay, and decisions are
    /// carried out in the order `decide` asks for (cancel, evict, fetch).
    struct World {
        config: PagerConfig,
        /// Bytes each tile holds once delivered.
        sizes: Vec<u64>,
        resident: Vec<u64>,
        in_flight: Vec<bool>,
        /// Frames left before an in-flight tile lands.
        arrives_in: Vec<u32>,
        /// Bytes of the latest non-empty fetch list.
        latest_fetch_bytes: u64,
        /// Whether the pager is told `sizes` before fetching (predicted admission).
        predict: bool,
    }

    impl World {
        fn new(config: PagerConfig, sizes: Vec<u64>) -> World {
            let tiles = config.tile_count();
            World {
                config,
                sizes,
                resident: vec![0; tiles],
                in_flight: vec![false; tiles],
                arrives_in: vec![0; tiles],
                latest_fetch_bytes: 0,
                predict: false,
            }
        }

        /// One frame: deliveries that are due, a decision, and its execution. A tile
        /// requested with delay `d` lands at the start of frame `d + 1` after the request.
        fn frame(&mut self, viewpoint: [f64; 2], delay: &mut dyn FnMut() -> u32) -> Decision {
            for i in 0..self.in_flight.len() {
                if self.in_flight[i] {
                    if self.arrives_in[i] == 0 {
                        self.in_flight[i] = false;
                        self.resident[i] = self.sizes[i];
                    } else {
                        self.arrives_in[i] -= 1;
                    }
                }
            }
            let view = PagerView {
                viewpoint,
                resident_bytes: &self.resident,
                in_flight: &self.in_flight,
                expected_bytes: self.predict.then_some(&self.sizes[..]),
            };
            let decision = decide(&self.config, &view);
            self.check_decision(&view, &decision);
            for &id in &decision.cancel {
                self.in_flight[self.config.index(id)] = false;
            }
            for &id in &decision.evict {
                self.resident[self.config.index(id)] = 0;
            }
            for &id in &decision.fetch {
                let i = self.config.index(id);
                self.in_flight[i] = true;
                self.arrives_in[i] = delay();
            }
            if !decision.fetch.is_empty() {
                self.latest_fetch_bytes = decision
                    .fetch
                    .iter()
                    .map(|&id| self.sizes[self.config.index(id)])
                    .sum();
            }
            self.check_square(&decision);
            decision
        }

        fn used(&self) -> u64 {
            self.resident.iter().sum()
        }

        fn nothing_in_flight(&self) -> bool {
            !self.in_flight.contains(&true)
        }

        fn square_bytes(&self, current: CurrentTile, belts: u32) -> u64 {
            square_tiles(&self.config, current, belts)
                .map(|id| self.sizes[self.config.index(id)])
                .sum()
        }

        /// Frames of a still viewpoint until a decision changes nothing; panics past `limit`.
        fn settle(
            &mut self,
            viewpoint: [f64; 2],
            delay: &mut dyn FnMut() -> u32,
            limit: u32,
        ) -> Decision {
            for _ in 0..limit {
                let decision = self.frame(viewpoint, delay);
                if decision.fetch.is_empty()
                    && decision.evict.is_empty()
                    && self.nothing_in_flight()
                {
                    return decision;
                }
            }
            panic!("a still viewpoint at {viewpoint:?} did not settle within {limit} frames");
        }

        /// What every decision must satisfy, seen from the state it was taken in.
        fn check_decision(&self, view: &PagerView<'_>, d: &Decision) {
            let config = &self.config;
            let resident = |id: TileId| view.resident_bytes[config.index(id)] > 0;
            let limit = config.memory_limit;
            assert_eq!(d.used_bytes, view.resident_bytes.iter().sum::<u64>());
            // 1. Resident bytes exceed the limit by at most the belt fetched last: every
            //    fetch starts at or under the limit with nothing in flight.
            assert!(
                d.used_bytes <= limit + self.latest_fetch_bytes,
                "{} bytes resident, limit {limit}, latest fetch {}",
                d.used_bytes,
                self.latest_fetch_bytes
            );
            // 2. The complete belts form the square (or clipped rectangle), and it is the
            //    largest: the next belt misses a tile.
            assert!(square_tiles(config, d.current, d.complete_belts).all(resident));
            assert!(
                d.complete_belts == d.belt_count
                    || !belt_tiles(config, d.current, d.complete_belts).all(resident)
            );
            assert_eq!(d.farthest_complete_belt, d.complete_belts.checked_sub(1));
            // 3. Nothing of the square is evicted; only resident tiles of one belt beyond it,
            //    over the limit, and never while loading.
            assert!(
                d.evict
                    .iter()
                    .all(|&id| resident(id) && belt_of(d.current, id) >= d.complete_belts)
            );
            assert!(
                d.evict
                    .windows(2)
                    .all(|w| belt_of(d.current, w[0]) == belt_of(d.current, w[1]))
            );
            // With sizes known, cached tiles beyond the belt being built also make room when
            // that belt does not fit under the limit (and only then).
            let next_belt_needs: u64 = belt_tiles(config, d.current, d.complete_belts)
                .filter(|&id| !resident(id))
                .map(|id| view.expected_bytes.map_or(0, |e| e[config.index(id)]))
                .sum();
            let making_room = view.expected_bytes.is_some()
                && d.complete_belts > 0
                && d.used_bytes + next_belt_needs > limit
                && d.evict
                    .iter()
                    .all(|&id| belt_of(d.current, id) > d.complete_belts);
            assert!(d.evict.is_empty() || ((d.used_bytes > limit || making_room) && !d.loading));
            // ...and that belt is the farthest holding any tile (the paper's dp); with nothing
            // evicted over the limit, every resident tile is in the square.
            let farthest = (0..config.tile_count())
                .filter(|&i| view.resident_bytes[i] > 0)
                .map(|i| {
                    belt_of(
                        d.current,
                        TileId::new(
                            (i % config.columns as usize) as u32,
                            (i / config.columns as usize) as u32,
                        ),
                    )
                })
                .max();
            if let Some(&evicted) = d.evict.first() {
                assert_eq!(Some(belt_of(d.current, evicted)), farthest);
            } else if d.used_bytes > limit && !d.loading {
                assert!(farthest.is_none_or(|far| far < d.complete_belts));
            }
            // Fetch: missing tiles of the belt being built, nearest first, at or under the limit.
            assert!(d.fetch.is_empty() || (d.used_bytes <= limit && !d.loading));
            assert!(
                d.fetch
                    .iter()
                    .all(|&id| !resident(id) && belt_of(d.current, id) == d.complete_belts)
            );
            let distance = |id: &TileId| {
                (f64::from(id.x) + 0.5 - view.viewpoint[0])
                    .hypot(f64::from(id.y) + 0.5 - view.viewpoint[1])
            };
            assert!(
                d.fetch
                    .windows(2)
                    .all(|w| distance(&w[0]) <= distance(&w[1]) + 1e-9)
            );
            // Cancel: exactly the in-flight tiles beyond the belt after the one being built.
            let in_flight: Vec<TileId> = (0..config.rows)
                .flat_map(|y| (0..config.columns).map(move |x| TileId::new(x, y)))
                .filter(|&id| view.in_flight[config.index(id)])
                .collect();
            let unwanted = |id: &&TileId| belt_of(d.current, **id) > d.complete_belts + 1;
            assert_eq!(
                d.cancel,
                in_flight
                    .iter()
                    .filter(unwanted)
                    .copied()
                    .collect::<Vec<_>>()
            );
            assert_eq!(d.loading, d.cancel.len() < in_flight.len());
        }

        /// 2 and 3 again after the decision is carried out: the square is still whole.
        fn check_square(&self, d: &Decision) {
            assert!(
                square_tiles(&self.config, d.current, d.complete_belts)
                    .all(|id| self.resident[self.config.index(id)] > 0)
            );
        }
    }

    #[test]
    fn a_still_viewpoint_from_empty_fetches_belt_0_then_belt_1_then_belt_2() {
        let config = PagerConfig::new(5, 5, 1000);
        let mut world = World::new(config, vec![1; 25]);
        let mut fetched = Vec::new();
        for _ in 0..5 {
            let decision = world.frame([2.5, 2.5], &mut || 0);
            let belts: Vec<u32> = decision
                .fetch
                .iter()
                .map(|&id| belt_of(decision.current, id))
                .collect();
            fetched.push((decision.complete_belts, belts.first().copied(), belts.len()));
        }
        // (complete belts, belt fetched, tiles fetched) per frame.
        assert_eq!(
            fetched,
            [
                (0, Some(0), 1),
                (1, Some(1), 8),
                (2, Some(2), 16),
                (3, None, 0),
                (3, None, 0)
            ]
        );
    }

    #[test]
    fn a_still_viewpoint_stops_at_the_largest_square_that_fits() {
        // Belt 1 is fetched at 1 byte used; the 3x3 square then holds 9 > 8 bytes, and stays.
        let config = PagerConfig::new(7, 7, 8);
        let mut world = World::new(config, vec![1; 49]);
        let decision = world.settle([3.5, 3.5], &mut || 2, 30);
        assert_eq!((decision.complete_belts, decision.used_bytes), (2, 9));
    }

    // --- properties over random grids, sizes, limits and walks ---------------------------

    /// splitmix64: per-tile sizes and delivery delays from one proptest seed.
    struct Random(u64);

    impl Random {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }

        fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }
    }

    #[derive(Debug, Clone)]
    enum Move {
        Stay(u32),
        Step(f64, f64),
        /// To a fraction of the grid's size on each axis; outside it below 0 and above 1.
        Jump(f64, f64),
    }

    fn moves() -> impl Strategy<Value = Move> {
        prop_oneof![
            1 => (1u32..6).prop_map(Move::Stay),
            4 => (-1.0f64..1.0, -1.0f64..1.0).prop_map(|(dx, dy)| Move::Step(dx, dy)),
            1 => (-0.3f64..1.3, -0.3f64..1.3).prop_map(|(fx, fy)| Move::Jump(fx, fy)),
        ]
    }

    /// A random world: grid, per-tile sizes of 1 to 1000 bytes, a limit from 0 (below any
    /// tile) to 120% of the whole grid, and the nearest-tile option on or off.
    fn world(
        columns: u32,
        rows: u32,
        seed: u64,
        limit_permille: u64,
        nearest: bool,
    ) -> (World, Random) {
        let mut random = Random(seed);
        let sizes: Vec<u64> = (0..columns * rows)
            .map(|_| 1 + random.below(1000))
            .collect();
        let limit = sizes.iter().sum::<u64>() * limit_permille / 1000;
        let config = PagerConfig {
            nearest_when_outside: nearest,
            ..PagerConfig::new(columns, rows, limit)
        };
        (World::new(config, sizes), random)
    }

    /// Delays of 0 to 4 frames; each belt then takes at most 6 frames, and settling (a fetch
    /// or an eviction per belt, at most 2 * belt_count + 1 of them) is bounded by this.
    const MAX_DELAY: u64 = 4;
    fn settle_limit(config: &PagerConfig) -> u32 {
        let belts = config.columns.max(config.rows) + 16; // grid plus the farthest walk off it
        (2 * belts + 2) * (MAX_DELAY as u32 + 2)
    }

    /// Flies `walk` from the grid's centre, one decision a frame, calling `after_frame`
    /// after each; returns where the walk ended.
    fn walk_frames(
        world: &mut World,
        random: &mut Random,
        walk: Vec<Move>,
        mut after_frame: impl FnMut(&World) -> Result<(), TestCaseError>,
    ) -> Result<[f64; 2], TestCaseError> {
        let (w, h) = (
            f64::from(world.config.columns),
            f64::from(world.config.rows),
        );
        let mut viewpoint = [w / 2.0, h / 2.0];
        for step in walk {
            let frames = match step {
                Move::Stay(frames) => frames,
                Move::Step(dx, dy) => {
                    viewpoint = [
                        (viewpoint[0] + dx).clamp(-8.0, w + 8.0),
                        (viewpoint[1] + dy).clamp(-8.0, h + 8.0),
                    ];
                    1
                }
                Move::Jump(fx, fy) => {
                    viewpoint = [fx * w, fy * h];
                    1
                }
            };
            for _ in 0..frames {
                // `World::frame` checks every decision (properties 1 to 3).
                world.frame(viewpoint, &mut || random.below(MAX_DELAY + 1) as u32);
                after_frame(world)?;
            }
        }
        Ok(viewpoint)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(192))]

        #[test]
        fn a_still_viewpoint_from_empty_settles_on_the_largest_square_that_fits(
            columns in 1u32..=24, rows in 1u32..=24, seed in any::<u64>(), limit_permille in 0u64..=1200, nearest in any::<bool>(),
            fx in -0.3f64..1.3, fy in -0.3f64..1.3,
        ) {
            let (mut world, mut random) = world(columns, rows, seed, limit_permille, nearest);
            let viewpoint = [fx * f64::from(columns), fy * f64::from(rows)];
            let limit = settle_limit(&world.config);
            let d = world.settle(viewpoint, &mut || random.below(MAX_DELAY + 1) as u32, limit);
            let k = d.complete_belts;
            // Nothing outside the square was ever fetched.
            prop_assert_eq!(world.used(), world.square_bytes(d.current, k));
            prop_assert!(k >= 1 || d.belt_count == 0);
            if k < d.belt_count {
                let memory_limit = world.config.memory_limit;
                prop_assert!(world.square_bytes(d.current, k) > memory_limit);
                prop_assert!(world.square_bytes(d.current, k - 1) <= memory_limit);
            }
        }

        #[test]
        fn every_frame_of_a_random_walk_keeps_the_square_and_the_limit_and_a_still_viewpoint_then_settles(
            columns in 1u32..=24, rows in 1u32..=24, seed in any::<u64>(), limit_permille in 0u64..=1200, nearest in any::<bool>(),
            walk in proptest::collection::vec(moves(), 1..80),
        ) {
            let (mut world, mut random) = world(columns, rows, seed, limit_permille, nearest);
            let viewpoint = walk_frames(&mut world, &mut random, walk, |_| Ok(()))?;
            let limit = settle_limit(&world.config);
            let d = world.settle(viewpoint, &mut || random.below(MAX_DELAY + 1) as u32, limit);
            // Settled: either everything is resident, or memory is over the limit and every
            // tile outside the square has been dropped.
            if d.complete_belts < d.belt_count {
                prop_assert!(world.used() > world.config.memory_limit);
                prop_assert_eq!(world.used(), world.square_bytes(d.current, d.complete_belts));
            }
        }

        #[test]
        fn with_sizes_known_a_still_viewpoint_from_empty_settles_on_the_largest_square_under_the_limit(
            columns in 1u32..=24, rows in 1u32..=24, seed in any::<u64>(), limit_permille in 0u64..=1200, nearest in any::<bool>(),
            fx in -0.3f64..1.3, fy in -0.3f64..1.3,
        ) {
            let (mut world, mut random) = world(columns, rows, seed, limit_permille, nearest);
            world.predict = true;
            let viewpoint = [fx * f64::from(columns), fy * f64::from(rows)];
            let limit = settle_limit(&world.config);
            let d = world.settle(viewpoint, &mut || random.below(MAX_DELAY + 1) as u32, limit);
            let (k, memory_limit) = (d.complete_belts, world.config.memory_limit);
            prop_assert_eq!(world.used(), world.square_bytes(d.current, k));
            prop_assert!(k >= 1 || d.belt_count == 0);
            // The current tile is always fetched; any larger square fits under the limit...
            if k > 1 {
                prop_assert!(world.square_bytes(d.current, k) <= memory_limit);
            }
            // ...and one more belt would not.
            if k < d.belt_count {
                prop_assert!(world.square_bytes(d.current, k + 1) > memory_limit);
            }
        }

        #[test]
        fn with_sizes_known_resident_bytes_exceed_the_limit_by_the_current_tile_at_most(
            columns in 1u32..=24, rows in 1u32..=24, seed in any::<u64>(), limit_permille in 0u64..=1200, nearest in any::<bool>(),
            walk in proptest::collection::vec(moves(), 1..80),
        ) {
            let (mut world, mut random) = world(columns, rows, seed, limit_permille, nearest);
            world.predict = true;
            let largest_tile = world.sizes.iter().copied().max().unwrap_or(0);
            let viewpoint = walk_frames(&mut world, &mut random, walk, |world| {
                prop_assert!(world.used() <= world.config.memory_limit + largest_tile,
                    "{} bytes resident, limit {} + one tile {}", world.used(), world.config.memory_limit, largest_tile);
                Ok(())
            })?;
            let limit = settle_limit(&world.config);
            let d = world.settle(viewpoint, &mut || random.below(MAX_DELAY + 1) as u32, limit);
            // Settled short of the whole grid: the next belt does not fit, and nothing beyond
            // the belt being built is still held.
            if d.complete_belts < d.belt_count {
                prop_assert!(world.square_bytes(d.current, d.complete_belts + 1) > world.config.memory_limit);
                let beyond = (0..world.config.tile_count())
                    .filter(|&i| world.resident[i] > 0)
                    .map(|i| TileId::new(i as u32 % columns, i as u32 / columns))
                    .filter(|&id| belt_of(d.current, id) > d.complete_belts)
                    .count();
                prop_assert_eq!(beyond, 0);
            }
        }
    }
}
