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
//! The module owns these rules and nothing else. The caller (`crate::scene::Scene::update`)
//! owns fetching, decoding and counting each tile's bytes (with what the level-of-detail
//! method holds for it), the limit (the budget's percentage, `memory`, less what the method
//! holds for no tile), and carrying a [`Decision`] out: cancel, evict, request, then report
//! the new state on the next frame.
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
    /// Fetch the current tile even when it alone would take the resident bytes over the
    /// limit (the paper's rule, so there is always something to draw; on by default). Off,
    /// as for a finer level of a pyramid whose coarser levels already draw, that tile
    /// waits until evicting cached belts makes room for it, and the limit always holds.
    /// Only with sizes known ([`PagerView::expected_bytes`]).
    pub current_over_limit: bool,
}

impl PagerConfig {
    /// A grid and a limit, with the nearest tile current when the viewpoint is off the terrain.
    pub const fn new(columns: u32, rows: u32, memory_limit: u64) -> PagerConfig {
        PagerConfig {
            columns,
            rows,
            memory_limit,
            nearest_when_outside: true,
            current_over_limit: true,
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
///    15,500, in the pager bench's flight). With sizes known, tiles within the largest
///    square that fits the limit around the current tile ([`fitting_belts`]) are kept too:
///    the square would fetch them anyway, and a viewpoint that crosses tiles faster than a
///    request lands would otherwise cancel every request before it lands.
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

    // The tiles of the belt being built, and of the one after it, stay in flight; so do,
    // with sizes known, those within the largest square that fits the limit, which the
    // square would fetch anyway as it grows. Any other in-flight tile belongs to a square
    // the viewpoint has left. In-flight tiles are few (one belt at most), so the flags are
    // scanned a block at a time: an OR over a block is branch-free and cheap.
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
    if !cancel.is_empty()
        && let Some(expected) = view.expected_bytes
    {
        // On a slow link the viewpoint may cross several tiles while a request is on its
        // way; cancelling it then, only to ask for it again once the square grows back,
        // meant that nothing ever landed (2 s a request, a tile crossed every 0.47 s).
        let reach = fitting_belts(config, current, expected);
        cancel.retain(|&id| belt_of(current, id) >= reach);
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
        // Predicted admission: a belt beyond the current tile (or, with `current_over_limit`
        // off, the current tile too) starts only if all of it fits. When it does not, the farthest belt beyond it (cached tiles the square does not
        // use) makes room, one belt a frame; when nothing is left to drop, the square has
        // reached the largest size that fits and stays.
        if let Some(expected) = view.expected_bytes
            && (complete_belts > 0 || !config.current_over_limit)
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

/// Belts around `current` whose tiles together fit `config.memory_limit` at the sizes
/// `expected` gives: belts `0..n` make the largest square the pager can hold there.
pub fn fitting_belts(config: &PagerConfig, current: CurrentTile, expected: &[u64]) -> u32 {
    let mut total = 0u64;
    for belt in 0..belt_count(config, current) {
        total = belt_tiles(config, current, belt)
            .map(|id| expected[config.index(id)])
            .fold(total, u64::saturating_add);
        if total > config.memory_limit {
            return belt;
        }
    }
    belt_count(config, current)
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

/// How the memory limit is shared between the levels of a pyramid, each of which runs
/// [`decide`] on its own grid within its share: `whole[k]` is what level `k` holds with
/// every tile resident (level 0 first). The coarsest level (one tile) gets what it needs
/// whole before any other gets a byte, so there is always something to draw; then, coarse
/// to fine, each level gets an equal part of what the coarser levels left, but no more than
/// its whole grid needs; what it does not need goes to the finer levels.
///
/// Equal parts: seen in perspective, a tile at distance `d` needs samples about `d` apart,
/// so level `k` serves the ring from `2^k` to `2^(k+1)` units of distance, whose area is
/// `4^k` times level 0's and whose tiles are `4^k` times larger: every level needs the same
/// number of tiles for its ring, as in geometry clipmaps, where every level is a square of
/// the same size.
pub fn level_shares(limit: u64, whole: &[u64]) -> Vec<u64> {
    shares_by(LevelPolicy::Equal, limit, whole)
}

/// How the levels of a pyramid share the memory limit (the default, [`LevelPolicy::Equal`],
/// is [`level_shares`]; `bench levels` measures both).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum LevelPolicy {
    /// The coarsest level whole, then equal parts coarse to fine ([`level_shares`]).
    #[default]
    Equal,
    /// The coarsest level whole, then level 0 all it can hold, then level 1, and so on:
    /// the largest full-resolution square, coarser levels only with what is left.
    FinestFirst,
}

/// The shares of the levels under `policy` (see [`level_shares`] for `whole`).
pub fn shares_by(policy: LevelPolicy, limit: u64, whole: &[u64]) -> Vec<u64> {
    let mut shares = vec![0; whole.len()];
    if policy == LevelPolicy::FinestFirst {
        let Some((coarsest, finer)) = whole.split_last() else {
            return shares;
        };
        let mut left = limit;
        let top = finer.len();
        shares[top] = (*coarsest).min(left);
        left -= shares[top];
        for (k, need) in finer.iter().enumerate() {
            shares[k] = (*need).min(left);
            left -= shares[k];
        }
        return shares;
    }
    let mut left = limit;
    for (k, need) in whole.iter().enumerate().rev() {
        let part = if k + 1 == whole.len() {
            left
        } else {
            left / (k as u64 + 1)
        };
        let share = part.min(*need);
        shares[k] = share;
        left -= share;
    }
    shares
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

    // --- many frames: a simulated fetcher, checked against what the pager promises -------
    //
    // The checks below state outcomes, taken from the module docs, ARCHITECTURE.md's
    // invariants on the pager and the paper's section 4: what is resident, requested,
    // dropped and cancelled after each frame, and where a still viewpoint comes to rest.
    // They work everything out by brute force over the grid (rings, squares, byte sums,
    // the largest square that fits) and call none of the module's helpers (`current_tile`,
    // `belt_of`, `belt_tiles`, `square_tiles`), so a wrong rule in `decide` shows up as a
    // broken promise instead of being reproduced by the checker. Every message names the
    // promise it checks, in brackets.

    /// Every tile of the grid, row-major, with its slot in the per-tile slices.
    fn grid(config: &PagerConfig) -> impl Iterator<Item = (usize, TileId)> + use<> {
        let (columns, rows) = (config.columns, config.rows);
        (0..rows)
            .flat_map(move |y| (0..columns).map(move |x| TileId::new(x, y)))
            .enumerate()
    }

    fn slot(config: &PagerConfig, id: TileId) -> usize {
        id.y as usize * config.columns as usize + id.x as usize
    }

    /// The tile under the viewpoint (tile `(i, j)` spans `[i, i+1) x [j, j+1)`); with the
    /// nearest-tile option, the grid tile nearest to it, found by clamping each coordinate.
    fn viewpoint_tile(config: &PagerConfig, viewpoint: [f64; 2]) -> (i64, i64) {
        let axis = |v: f64, tiles: u32| {
            let tile = v.floor() as i64;
            if config.nearest_when_outside {
                tile.clamp(0, i64::from(tiles) - 1)
            } else {
                tile
            }
        };
        (
            axis(viewpoint[0], config.columns),
            axis(viewpoint[1], config.rows),
        )
    }

    /// How many tiles out from `centre` `id` lies (the Chebyshev distance): its ring.
    fn ring(centre: (i64, i64), id: TileId) -> u64 {
        centre
            .0
            .abs_diff(i64::from(id.x))
            .max(centre.1.abs_diff(i64::from(id.y)))
    }

    /// Rings needed around `centre` to cover the grid: one more than the farthest tile's.
    fn rings(config: &PagerConfig, centre: (i64, i64)) -> u64 {
        grid(config)
            .map(|(_, id)| ring(centre, id) + 1)
            .max()
            .unwrap_or(0)
    }

    /// How many rings around `centre` hold only resident tiles (the square of complete
    /// belts): the ring of the nearest missing tile, or every ring when none is missing.
    fn complete_rings(config: &PagerConfig, centre: (i64, i64), resident: &[u64]) -> u64 {
        grid(config)
            .filter(|&(i, _)| resident[i] == 0)
            .map(|(_, id)| ring(centre, id))
            .min()
            .unwrap_or_else(|| rings(config, centre))
    }

    /// Bytes of the tiles in rings `0..k` around `centre`: the square of `k` belts.
    fn square_bytes(config: &PagerConfig, sizes: &[u64], centre: (i64, i64), k: u64) -> u64 {
        grid(config)
            .filter(|&(_, id)| ring(centre, id) < k)
            .map(|(i, _)| sizes[i])
            .sum()
    }

    /// The most rings around `centre` whose tiles together fit under the limit, trying
    /// every count.
    fn largest_square_that_fits(config: &PagerConfig, sizes: &[u64], centre: (i64, i64)) -> u64 {
        (0..=rings(config, centre))
            .filter(|&k| square_bytes(config, sizes, centre, k) <= config.memory_limit)
            .max()
            .unwrap_or(0)
    }

    /// Where the square of a still viewpoint comes to rest, from nothing resident: without
    /// sizes known, the paper's rule fetches a belt whenever memory is at or under the limit,
    /// so the square ends one belt past the largest that fits (that belt overspends); with
    /// sizes known, the largest that fits, but never less than the current tile.
    fn resting_square(
        config: &PagerConfig,
        sizes: &[u64],
        centre: (i64, i64),
        predict: bool,
    ) -> u64 {
        let fits = largest_square_that_fits(config, sizes, centre);
        // The current tile comes over the limit only as the paper's rule has it.
        let k = if !predict {
            fits + 1
        } else if config.current_over_limit {
            fits.max(1)
        } else {
            fits
        };
        k.min(rings(config, centre))
    }

    /// The caller's side of the pager, simulated: tiles land after a delay, and decisions are
    /// carried out in the order `decide` asks for (cancel, evict, fetch). Every frame is
    /// checked by [`World::check`].
    struct World {
        config: PagerConfig,
        /// Bytes each tile holds once delivered.
        sizes: Vec<u64>,
        resident: Vec<u64>,
        in_flight: Vec<bool>,
        /// Frames left before an in-flight tile lands.
        arrives_in: Vec<u32>,
        /// Whether the pager is told `sizes` before fetching (predicted admission).
        predict: bool,
        /// The latest non-empty request.
        requested: Vec<TileId>,
        /// How far the latest request may take resident bytes over the limit: all of it
        /// without sizes known; with them, only a lone current tile.
        overspend: u64,
        /// The viewpoint's tile and the rings complete around it, at the previous decision.
        previous: Option<((i64, i64), u64)>,
        /// Tiles evicted and cancelled so far.
        evicted: usize,
        cancelled: usize,
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
                predict: false,
                requested: Vec::new(),
                overspend: 0,
                previous: None,
                evicted: 0,
                cancelled: 0,
            }
        }

        /// One frame: deliveries that are due, a decision, its execution, and the checks.
        /// A tile requested with delay `d` lands at the start of frame `d + 1` after the
        /// request.
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
            let (resident, in_flight) = (self.resident.clone(), self.in_flight.clone());
            let decision = decide(
                &self.config,
                &PagerView {
                    viewpoint,
                    resident_bytes: &resident,
                    in_flight: &in_flight,
                    expected_bytes: self.predict.then_some(&self.sizes[..]),
                },
            );
            for &id in &decision.cancel {
                self.in_flight[slot(&self.config, id)] = false;
            }
            for &id in &decision.evict {
                self.resident[slot(&self.config, id)] = 0;
            }
            for &id in &decision.fetch {
                let i = slot(&self.config, id);
                self.in_flight[i] = true;
                self.arrives_in[i] = delay();
            }
            self.check(viewpoint, &resident, &in_flight, &decision);
            decision
        }

        fn used(&self) -> u64 {
            self.resident.iter().sum()
        }

        fn nothing_in_flight(&self) -> bool {
            !self.in_flight.contains(&true)
        }

        /// Frames of a still viewpoint until a frame requests and drops nothing with nothing
        /// in flight; panics past `limit`. `decide` being pure, the next frame would see the
        /// same state and decide the same: the pager is at rest.
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
            panic!(
                "[comes to rest] a still viewpoint at {viewpoint:?} did not settle within {limit} frames"
            );
        }

        /// Checks one frame against the pager's promises. `resident` and `in_flight` are the
        /// state the decision was taken in (after this frame's deliveries); `self` is the
        /// state after carrying the decision out.
        fn check(
            &mut self,
            viewpoint: [f64; 2],
            resident: &[u64],
            in_flight: &[bool],
            d: &Decision,
        ) {
            let config = self.config;
            let limit = config.memory_limit;
            let centre = viewpoint_tile(&config, viewpoint);
            let k = complete_rings(&config, centre, resident);
            let ring = |id: TileId| ring(centre, id);
            let was_resident = |id: TileId| resident[slot(&config, id)] > 0;
            let was_in_flight = |id: TileId| in_flight[slot(&config, id)];
            let used: u64 = resident.iter().sum();
            let used_after = self.used();
            let centre_tile = grid(&config).map(|(_, id)| id).find(|&id| ring(id) == 0);
            let sorted = |ids: &[TileId]| {
                let mut ids = ids.to_vec();
                ids.sort();
                ids
            };
            let flying: Vec<TileId> = grid(&config)
                .filter(|&(i, _)| in_flight[i])
                .map(|(_, id)| id)
                .collect();
            let flying_after: Vec<TileId> = grid(&config)
                .filter(|&(i, _)| self.in_flight[i])
                .map(|(_, id)| id)
                .collect();
            let still_flying = flying.iter().filter(|id| !d.cancel.contains(id)).count();
            let farthest_resident = grid(&config)
                .filter(|&(i, _)| resident[i] > 0)
                .map(|(_, id)| ring(id))
                .max();
            let missing_next: u64 = grid(&config)
                .filter(|&(i, id)| resident[i] == 0 && ring(id) == k)
                .map(|(i, _)| self.sizes[i])
                .sum();

            // [report] The decision describes the state as it is.
            assert_eq!((d.current.x, d.current.y), centre, "[report] current tile");
            assert_eq!(
                u64::from(d.belt_count),
                rings(&config, centre),
                "[report] belt count"
            );
            assert_eq!(
                u64::from(d.complete_belts),
                k,
                "[report] complete belts: rings whose tiles are all resident"
            );
            assert_eq!(
                d.farthest_complete_belt.map(u64::from),
                k.checked_sub(1),
                "[report] farthest complete belt"
            );
            assert_eq!(d.used_bytes, used, "[report] used bytes");
            assert_eq!(d.loading, still_flying > 0, "[report] loading");

            // [consistent] No tile twice in a list; nothing resident or in flight requested,
            // only resident tiles dropped, only in-flight tiles cancelled; nothing both
            // requested and dropped.
            for (name, list) in [
                ("fetch", &d.fetch),
                ("evict", &d.evict),
                ("cancel", &d.cancel),
            ] {
                let mut unique = sorted(list);
                unique.dedup();
                assert_eq!(
                    unique.len(),
                    list.len(),
                    "[consistent] {name} repeats a tile: {list:?}"
                );
            }
            assert!(
                d.fetch
                    .iter()
                    .all(|&id| !was_resident(id) && !was_in_flight(id)),
                "[consistent] a resident or in-flight tile is requested: {:?}",
                d.fetch
            );
            assert!(
                d.evict.iter().all(|&id| was_resident(id)),
                "[consistent] a tile not resident is evicted: {:?}",
                d.evict
            );
            assert!(
                d.cancel.iter().all(|&id| was_in_flight(id)),
                "[consistent] a tile not in flight is cancelled: {:?}",
                d.cancel
            );
            assert!(
                !d.fetch.iter().any(|id| d.evict.contains(id)),
                "[consistent] a tile is both requested and evicted"
            );

            // [square kept] A complete belt of the current square is never evicted: the
            // square is whole after the frame. With the viewpoint on the same tile as in the
            // previous frame, the square never shrinks (the paper's stability).
            assert!(
                grid(&config)
                    .filter(|&(_, id)| ring(id) < k)
                    .all(|(i, _)| self.resident[i] > 0),
                "[square kept] a tile of the {k} complete rings around {centre:?} was evicted: {:?}",
                d.evict
            );
            if let Some((previous_centre, previous_k)) = self.previous
                && previous_centre == centre
            {
                assert!(
                    k >= previous_k,
                    "[square kept] the square around {centre:?} shrank from {previous_k} to {k} rings"
                );
            }
            self.previous = Some((centre, k));

            // [one belt at a time] Nothing is requested or dropped while requested tiles are
            // still in flight, so whatever is in flight after the frame is from one request.
            assert!(
                still_flying == 0 || (d.fetch.is_empty() && d.evict.is_empty()),
                "[one belt at a time] {still_flying} tiles in flight, yet fetch {:?} evict {:?}",
                d.fetch,
                d.evict
            );

            // [by belts] A request is the whole of the nearest incomplete ring's missing
            // tiles, nearest to the viewpoint first, started at or under the limit; with
            // sizes known, only if it fits whole, except the current tile alone.
            if !d.fetch.is_empty() {
                let ring_k: Vec<TileId> = grid(&config)
                    .filter(|&(i, id)| resident[i] == 0 && ring(id) == k)
                    .map(|(_, id)| id)
                    .collect();
                assert_eq!(
                    sorted(&d.fetch),
                    sorted(&ring_k),
                    "[by belts] the request is not the missing tiles of ring {k}"
                );
                let distance = |id: &TileId| {
                    (f64::from(id.x) + 0.5 - viewpoint[0])
                        .hypot(f64::from(id.y) + 0.5 - viewpoint[1])
                };
                assert!(
                    d.fetch
                        .windows(2)
                        .all(|w| distance(&w[0]) <= distance(&w[1]) + 1e-9),
                    "[by belts] not nearest first: {:?}",
                    d.fetch
                );
                let bytes: u64 = d
                    .fetch
                    .iter()
                    .map(|&id| self.sizes[slot(&config, id)])
                    .sum();
                let lone_current = config.current_over_limit
                    && d.fetch.len() == 1
                    && Some(d.fetch[0]) == centre_tile;
                assert!(
                    used <= limit,
                    "[limit] a belt is requested with {used} bytes resident over the limit {limit}"
                );
                if self.predict {
                    assert!(
                        used + bytes <= limit || lone_current,
                        "[limit] with sizes known, a belt of {bytes} bytes that does not fit ({used} resident, limit {limit}) is requested"
                    );
                }
                self.requested = d.fetch.clone();
                self.overspend = if !self.predict || lone_current {
                    bytes
                } else {
                    0
                };
            }
            assert!(
                flying_after.iter().all(|id| self.requested.contains(id)),
                "[one belt at a time] tiles of two requests in flight"
            );

            // [limit] Resident bytes exceed the limit by at most the belt requested last
            // (with sizes known, by at most a lone current tile).
            assert!(
                used_after <= limit + self.overspend,
                "[limit] {used_after} bytes resident, limit {limit}, latest request may overspend by {}",
                self.overspend
            );

            // [evict] One ring a frame, the farthest holding a tile, all of it; under the
            // limit, tiles outside the square stay cached, except, with sizes known, those
            // beyond the next ring, to make room for it when it does not fit.
            if let Some(&first) = d.evict.first() {
                let r = ring(first);
                assert!(
                    d.evict.iter().all(|&id| ring(id) == r),
                    "[evict] more than one ring evicted: {:?}",
                    d.evict
                );
                assert!(
                    grid(&config)
                        .filter(|&(i, _)| self.resident[i] > 0)
                        .all(|(_, id)| ring(id) < r),
                    "[evict] ring {r} evicted while a tile as far or farther stays"
                );
                assert!(
                    used > limit || (self.predict && r > k && used + missing_next > limit),
                    "[evict] ring {r} evicted under the limit ({used} of {limit} bytes, {k} complete rings, {missing_next} bytes missing from ring {k})"
                );
                self.evicted += d.evict.len();
            }

            // [cancel] What the square wants now or next (its ring being built and the one
            // after) is not cancelled; after the frame nothing farther is in flight, so a
            // jump does not wait for the square it left.
            assert!(
                d.cancel.iter().all(|&id| ring(id) > k + 1),
                "[cancel] a tile within ring {} of {centre:?} is cancelled: {:?}",
                k + 1,
                d.cancel
            );
            // With sizes known, tiles within the largest square that fits stay in flight.
            let keep = if self.predict {
                let mut fitting = 0;
                while fitting < rings(&config, centre)
                    && grid(&config)
                        .filter(|&(_, id)| ring(id) <= fitting)
                        .map(|(i, _)| self.sizes[i])
                        .sum::<u64>()
                        <= limit
                {
                    fitting += 1;
                }
                (k + 1).max(fitting.saturating_sub(1))
            } else {
                k + 1
            };
            assert!(
                flying_after.iter().all(|&id| ring(id) <= keep),
                "[cancel] a tile beyond ring {keep} of {centre:?} is still in flight: {:?}",
                flying_after
            );
            assert!(
                d.cancel.iter().all(|&id| ring(id) > keep),
                "[cancel] a tile within ring {keep} of {centre:?}, which fits, is cancelled: {:?}",
                d.cancel
            );
            self.cancelled += d.cancel.len();

            // [jump] A missing current tile is requested, first, in the frame the viewpoint
            // reaches it, unless the new square's own tiles are in flight or memory is over
            // the limit (or, with `current_over_limit` off, it would take it over).
            if let Some(tile) = centre_tile
                && !was_resident(tile)
                && still_flying == 0
                && used <= limit
                && (config.current_over_limit
                    || !self.predict
                    || used + self.sizes[slot(&config, tile)] <= limit)
            {
                assert_eq!(
                    d.fetch.first(),
                    Some(&tile),
                    "[jump] the missing current tile is not requested at once"
                );
            }

            // [progress] With nothing in flight, the pager requests or drops something
            // exactly while it is not at rest. At rest: every tile is resident; or over the
            // limit with nothing outside the square to drop; or, with sizes known, at least
            // the current tile held, the next ring does not fit and nothing beyond it is held.
            let at_rest = k == rings(&config, centre)
                || (used > limit && farthest_resident.is_none_or(|f| f < k))
                || (self.predict
                    && (k >= 1 || !config.current_over_limit)
                    && used <= limit
                    && used + missing_next > limit
                    && farthest_resident.is_none_or(|f| f <= k));
            if still_flying == 0 {
                assert_eq!(
                    d.fetch.is_empty() && d.evict.is_empty(),
                    at_rest,
                    "[progress] idle is not the same as at rest: {k} complete rings of {}, {used} bytes, limit {limit}, farthest resident ring {farthest_resident:?}, fetch {:?}, evict {:?}",
                    rings(&config, centre),
                    d.fetch,
                    d.evict
                );
            }
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
    fn without_the_current_tile_over_the_limit_a_move_makes_room_first_and_the_limit_holds() {
        // A row of four 4-byte tiles and 8 bytes: from tile 0 the square holds tiles 0 and 1.
        // Moved to tile 3, the current tile alone would take 12 bytes.
        let peak = |current_over_limit: bool| {
            let config = PagerConfig {
                current_over_limit,
                ..PagerConfig::new(4, 1, 8)
            };
            let mut world = World::new(config, vec![4; 4]);
            world.predict = true;
            world.settle([0.5, 0.5], &mut || 0, 10);
            assert_eq!(world.resident, [4, 4, 0, 0]);
            let mut peak = 0;
            for _ in 0..10 {
                // Bytes resident when the pager decides, deliveries included.
                peak = peak.max(world.frame([3.5, 0.5], &mut || 0).used_bytes);
            }
            (peak, world.resident.clone())
        };
        // The paper's rule fetches tile 3 at once and overspends by it...
        assert_eq!(peak(true).0, 12);
        // ...while without it tile 0, then tile 1, make room: the same square, never over.
        assert_eq!(peak(false), (8, vec![0, 0, 4, 4]));
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
    /// tile) to 120% of the whole grid, the nearest-tile option on or off, sizes told to
    /// the pager or not, and then (by the seed) the current tile fetched over the limit or
    /// not.
    fn world(
        columns: u32,
        rows: u32,
        seed: u64,
        limit_permille: u64,
        nearest: bool,
        predict: bool,
    ) -> (World, Random) {
        let mut random = Random(seed);
        let sizes: Vec<u64> = (0..columns * rows)
            .map(|_| 1 + random.below(1000))
            .collect();
        let limit = sizes.iter().sum::<u64>() * limit_permille / 1000;
        let config = PagerConfig {
            nearest_when_outside: nearest,
            current_over_limit: !predict || !seed.is_multiple_of(3),
            ..PagerConfig::new(columns, rows, limit)
        };
        let mut world = World::new(config, sizes);
        world.predict = predict;
        (world, random)
    }

    /// Delays of 0 to 4 frames: a request lands within MAX_DELAY + 1 frames.
    const MAX_DELAY: u64 = 4;

    /// Frames a still viewpoint may take to come to rest after a walk: a request or an
    /// eviction per ring (at most 2 * rings + 1 of them), each done within MAX_DELAY + 2.
    fn settle_limit(config: &PagerConfig) -> u32 {
        let belts = config.columns.max(config.rows) + 16; // grid plus the farthest walk off it
        (2 * belts + 2) * (MAX_DELAY as u32 + 2)
    }

    /// Flies `walk` from the grid's centre, one decision a frame (each checked by
    /// [`World::check`]); returns where the walk ended.
    fn walk_frames(world: &mut World, random: &mut Random, walk: Vec<Move>) -> [f64; 2] {
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
                world.frame(viewpoint, &mut || random.below(MAX_DELAY + 1) as u32);
            }
        }
        viewpoint
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(192))]

        /// [converges] From nothing resident, a still viewpoint's square grows, a frame never
        /// idle until it rests, to the largest square that fits (computed by trying every
        /// count of rings); exactly that square is resident, and nothing was ever evicted or
        /// cancelled.
        #[test]
        fn a_still_viewpoint_from_empty_grows_to_the_largest_square_that_fits_and_rests(
            columns in 1u32..=24, rows in 1u32..=24, seed in any::<u64>(),
            limit_permille in 0u64..=1200, nearest in any::<bool>(), predict in any::<bool>(),
            fx in -0.3f64..1.3, fy in -0.3f64..1.3,
        ) {
            let (mut world, mut random) =
                world(columns, rows, seed, limit_permille, nearest, predict);
            let viewpoint = [fx * f64::from(columns), fy * f64::from(rows)];
            let centre = viewpoint_tile(&world.config, viewpoint);
            let target = resting_square(&world.config, &world.sizes, centre, predict);
            // A ring lands within MAX_DELAY + 1 frames of its request and the next ring is
            // requested in the frame after; at most every ring is requested.
            let frames = (rings(&world.config, centre) as u32 + 1) * (MAX_DELAY as u32 + 2);
            let mut rested = false;
            for frame in 0..frames {
                let d = world.frame(viewpoint, &mut || random.below(MAX_DELAY + 1) as u32);
                let busy = !d.fetch.is_empty() || !world.nothing_in_flight();
                let k = complete_rings(&world.config, centre, &world.resident);
                prop_assert!(k <= target,
                    "[converges] frame {}: {} rings complete, past the {} that fit", frame, k, target);
                if !busy {
                    prop_assert_eq!(k, target,
                        "[converges] frame {}: idle with {} of {} rings", frame, k, target);
                    rested = true;
                    break;
                }
            }
            prop_assert!(rested, "[converges] not at rest after {} frames", frames);
            let square: Vec<usize> = grid(&world.config)
                .filter(|&(_, id)| ring(centre, id) < target)
                .map(|(i, _)| i)
                .collect();
            let resident: Vec<usize> = (0..world.resident.len())
                .filter(|&i| world.resident[i] > 0)
                .collect();
            prop_assert_eq!(resident, square,
                "[converges] not exactly the square of {} rings is resident", target);
            prop_assert_eq!((world.evicted, world.cancelled), (0, 0),
                "[converges] tiles evicted or cancelled");
        }

        /// Every frame of a random walk keeps the promises [`World::check`] states; then a
        /// still viewpoint comes to rest [rest after a walk] with at least the largest square
        /// that fits (tiles cached on the way may complete a larger one, never dropped as it
        /// is complete) and no memory held for nothing: over the limit, only the square;
        /// under it, with sizes known, nothing beyond the next ring, which does not fit.
        #[test]
        fn every_frame_of_a_random_walk_keeps_the_pagers_promises_and_a_still_viewpoint_then_rests(
            columns in 1u32..=24, rows in 1u32..=24, seed in any::<u64>(),
            limit_permille in 0u64..=1200, nearest in any::<bool>(), predict in any::<bool>(),
            walk in proptest::collection::vec(moves(), 1..80),
        ) {
            let (mut world, mut random) =
                world(columns, rows, seed, limit_permille, nearest, predict);
            let viewpoint = walk_frames(&mut world, &mut random, walk);
            let limit = settle_limit(&world.config);
            world.settle(viewpoint, &mut || random.below(MAX_DELAY + 1) as u32, limit);
            let config = world.config;
            let centre = viewpoint_tile(&config, viewpoint);
            let all = rings(&config, centre);
            let k = complete_rings(&config, centre, &world.resident);
            let fits = largest_square_that_fits(&config, &world.sizes, centre);
            let least = resting_square(&config, &world.sizes, centre, predict);
            prop_assert!(k >= least, "[rest after a walk] {} complete rings, {} fit", k, fits);
            let farthest = grid(&config)
                .filter(|&(i, _)| world.resident[i] > 0)
                .map(|(_, id)| ring(centre, id))
                .max();
            if k < all {
                if world.used() > config.memory_limit {
                    prop_assert!(farthest.is_none_or(|f| f < k),
                        "[rest after a walk] over the limit with tiles outside the square");
                } else {
                    prop_assert!(predict,
                        "[rest after a walk] under the limit and not every tile resident");
                    prop_assert!(farthest.is_none_or(|f| f <= k),
                        "[rest after a walk] tiles beyond the next ring held");
                    prop_assert!(square_bytes(&config, &world.sizes, centre, k + 1) > config.memory_limit,
                        "[rest after a walk] the next ring would fit");
                }
            }
        }

        /// [jump] A jump far from a square still loading cancels every tile in flight for the
        /// old square and requests the new current tile in the same frame (when it may: with
        /// `current_over_limit` off and sizes known, not when it would pass the limit).
        #[test]
        fn a_jump_cancels_the_old_squares_requests_and_starts_the_new_square_in_the_same_frame(
            columns in 10u32..=24, rows in 1u32..=24, seed in any::<u64>(),
            limit_permille in 0u64..=1200, nearest in any::<bool>(), predict in any::<bool>(),
            requests in 1usize..=3,
            ax in 0.0f64..0.3, ay in 0.0f64..1.0, bx in 0.7f64..1.0, by in 0.0f64..1.0,
        ) {
            let (mut world, mut random) =
                world(columns, rows, seed, limit_permille, nearest, predict);
            let (w, h) = (f64::from(columns), f64::from(rows));
            let (a, b) = ([ax * w, ay * h], [bx * w, by * h]);
            // Delays of 1 to MAX_DELAY: the latest request is still in flight at the jump.
            let mut delay = || 1 + random.below(MAX_DELAY) as u32;
            // At A until its `requests`-th request (rings 0 to 2 around A, which on a grid 10
            // or more wide lie 2 or more tiles from B's tile, beyond the ring B's empty square
            // builds and the one after), or until it rests.
            let mut made = 0;
            for _ in 0..settle_limit(&world.config) {
                let d = world.frame(a, &mut delay);
                if !d.fetch.is_empty() {
                    made += 1;
                    if made == requests {
                        break;
                    }
                } else if world.nothing_in_flight() {
                    break;
                }
            }
            let old: Vec<TileId> = grid(&world.config)
                .filter(|&(i, _)| world.in_flight[i])
                .map(|(_, id)| id)
                .collect();
            let d = world.frame(b, &mut delay);
            // With sizes known, requests within the largest square that fits around B stay
            // (the frame's own check holds them to that); the others are cancelled.
            let keep = (d.complete_belts + 1).max(
                fitting_belts(&world.config, d.current, &world.sizes).saturating_sub(1),
            );
            let beyond: Vec<TileId> = old
                .iter()
                .copied()
                .filter(|&id| !world.predict || belt_of(d.current, id) > keep)
                .collect();
            let mut cancelled = d.cancel.clone();
            cancelled.sort_by_key(|id| (id.y, id.x));
            prop_assert_eq!(cancelled, beyond.clone(), "[jump] not every old request beyond the fitting square cancelled");
            // Unless, with sizes known and `current_over_limit` off, the new current tile
            // would take memory over the limit (bytes held at the decision: what is resident
            // now and what it evicted).
            let tile = TileId::new(b[0].floor() as u32, b[1].floor() as u32);
            let used = world.used()
                + d.evict.iter().map(|&id| world.sizes[slot(&world.config, id)]).sum::<u64>();
            let limit = world.config.memory_limit;
            let fits = world.config.current_over_limit
                || !world.predict
                || used + world.sizes[slot(&world.config, tile)] <= limit;
            if !old.is_empty() && beyond.len() == old.len() && used <= limit && fits {
                prop_assert_eq!(d.fetch, vec![tile],
                    "[jump] the new current tile is not requested at once");
            }
        }

        /// [levels] A pyramid of levels pages as nested squares: each level runs Algorithm 1
        /// on its own grid within its share of the limit ([`level_shares`]), around the tile
        /// of that level under the viewpoint; every frame of a random walk keeps every
        /// level's promises ([`World::check`]: a level's resident bytes stay within its share
        /// but for a lone current tile), so the levels together stay within the limit but
        /// for one tile a level; and a still viewpoint then brings each level to rest with at
        /// least the largest square that fits its share.
        #[test]
        fn every_level_of_a_pyramid_pages_its_own_square_within_its_share(
            width in 2u32..=260, height in 2u32..=260, power in 2u32..=4,
            seed in any::<u64>(), limit_permille in 0u64..=1200,
            walk in proptest::collection::vec(moves(), 1..40),
        ) {
            let tile_size = (1u32 << power) + 1;
            let rasters = terrain_shared::manifest::level_rasters(
                terrain_shared::manifest::RasterSize { width, height },
                tile_size,
            );
            let mut random = Random(seed);
            let grids: Vec<_> = rasters
                .iter()
                .map(|r| terrain_shared::manifest::grid_covering(*r, tile_size))
                .collect();
            let sizes: Vec<Vec<u64>> = grids
                .iter()
                .map(|g| (0..g.columns * g.rows).map(|_| 1 + random.below(1000)).collect())
                .collect();
            let whole: Vec<u64> = sizes.iter().map(|s| s.iter().sum()).collect();
            let limit = whole.iter().sum::<u64>() * limit_permille / 1000;
            let shares = level_shares(limit, &whole);
            prop_assert!(shares.iter().sum::<u64>() <= limit, "[levels] shares {:?} exceed {}", shares, limit);
            let mut worlds: Vec<World> = grids
                .iter()
                .zip(&shares)
                .zip(sizes)
                .map(|((g, &share), sizes)| {
                    let mut world = World::new(PagerConfig::new(g.columns, g.rows, share), sizes);
                    world.predict = true;
                    world
                })
                .collect();
            // The viewpoint in level-0 tiles; level k's tiles are 2^k times larger.
            let (w, h) = (f64::from(grids[0].columns), f64::from(grids[0].rows));
            let mut viewpoint = [w / 2.0, h / 2.0];
            let at = |v: [f64; 2], k: usize| [v[0] / f64::from(1u32 << k), v[1] / f64::from(1u32 << k)];
            let frame_all = |worlds: &mut Vec<World>, v: [f64; 2], random: &mut Random| {
                for (k, world) in worlds.iter_mut().enumerate() {
                    world.frame(at(v, k), &mut || random.below(MAX_DELAY + 1) as u32);
                }
                let lone: u64 = worlds.iter().map(|w| w.sizes.iter().max().copied().unwrap_or(0)).sum();
                let used: u64 = worlds.iter().map(World::used).sum();
                assert!(used <= limit + lone, "[levels] {used} bytes resident, limit {limit}");
            };
            for step in walk {
                let frames = match step {
                    Move::Stay(frames) => frames,
                    Move::Step(dx, dy) => {
                        viewpoint = [(viewpoint[0] + dx).clamp(-8.0, w + 8.0), (viewpoint[1] + dy).clamp(-8.0, h + 8.0)];
                        1
                    }
                    Move::Jump(fx, fy) => {
                        viewpoint = [fx * w, fy * h];
                        1
                    }
                };
                for _ in 0..frames {
                    frame_all(&mut worlds, viewpoint, &mut random);
                }
            }
            for (k, world) in worlds.iter_mut().enumerate() {
                let limit = settle_limit(&world.config);
                world.settle(at(viewpoint, k), &mut || random.below(MAX_DELAY + 1) as u32, limit);
                let centre = viewpoint_tile(&world.config, at(viewpoint, k));
                let complete = complete_rings(&world.config, centre, &world.resident);
                let fits = largest_square_that_fits(&world.config, &world.sizes, centre);
                prop_assert!(complete >= fits.max(1).min(rings(&world.config, centre)),
                    "[levels] level {}: {} rings complete, {} fit its share", k, complete, fits);
            }
        }
    }

    #[test]
    fn levels_share_the_limit_coarsest_first_in_equal_parts_and_pass_on_what_they_do_not_need() {
        // Three levels: the coarsest needs 10, the middle 500, level 0 5000.
        assert_eq!(level_shares(3000, &[5000, 500, 10]), vec![2490, 500, 10]);
        assert_eq!(level_shares(1000, &[5000, 500, 10]), vec![495, 495, 10]);
        // The coarsest whole before any other gets a byte.
        assert_eq!(level_shares(10, &[5000, 500, 10]), vec![0, 0, 10]);
        assert_eq!(level_shares(9, &[5000, 500, 10]), vec![0, 0, 9]);
        // Enough for everything: each level its whole, the rest unused.
        assert_eq!(level_shares(1 << 20, &[5000, 500, 10]), vec![5000, 500, 10]);
        // One level: all of it.
        assert_eq!(level_shares(123, &[1000]), vec![123]);
        // Finest first: the coarsest whole, then level 0 before level 1.
        let finest = |limit| shares_by(LevelPolicy::FinestFirst, limit, &[5000, 500, 10]);
        assert_eq!(finest(3000), vec![2990, 0, 10]);
        assert_eq!(finest(5600), vec![5000, 500, 10]);
        assert_eq!(finest(5300), vec![5000, 290, 10]);
    }
}
