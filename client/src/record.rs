//! The records of a flight, a row of `flight.csv` per frame: what the flight writes and
//! the charts draw.

/// Columns of `flight.csv`, one row per frame. The render columns are empty with
/// `--no-render`; `gpu_ms` is empty where the adapter has no timestamp queries, the
/// `gpu_allocated` columns where the backend gives no allocator report, `rss_bytes` where
/// the OS reports no resident set, `predicted_ms` and `target_fps` where no target frame rate
/// applies.
pub const CSV_HEADER: &str = "frame,time_s,wall_s,x_m,y_m,z_m,ground_m,current_x,current_y,farthest_complete_belt,complete_belts,resident_tiles,resident_bytes,memory_limit_bytes,gpu_bytes,heap_bytes,gpu_allocated_bytes,gpu_allocated_terrain_bytes,gpu_reserved_bytes,rss_bytes,bytes_downloaded,in_flight,retries,evicted_unused_bytes,texture_budget_bytes,visible_tiles,triangles,triangles_needed,filler_triangles,draw_calls,global_budget,mask_levels,lod_ms,cpu_ms,gpu_ms,frame_ms,predicted_ms,fps,target_fps";

/// What a rendered frame adds to its record.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderRecord {
    pub visible_tiles: u32,
    /// Triangles of the tiles' masks.
    pub triangles: u64,
    /// The fewest mask triangles keeping every drawn tile within 1 pixel of screen-space
    /// error ([`crate::lod::needed`]).
    pub triangles_needed: u64,
    pub filler_triangles: u64,
    pub draw_calls: u32,
    /// Global triangle budget the frame was planned with.
    pub global_budget: u32,
    /// Tiles per mask level, `level:count` pairs, finest first.
    pub mask_levels: Vec<(u32, u32)>,
    /// Culling, importance, budget sharing and mask selection.
    pub lod_ms: f64,
    /// CPU time of the frame: paging and uploads, level of detail, command encoding.
    pub cpu_ms: f64,
    /// GPU time of the render pass (timestamp queries), when the adapter has them.
    pub gpu_ms: Option<f64>,
    /// The frame's wall time, from its start to the end of its draw: its paging, its
    /// recording and its wait for the frame before it (two frames are in flight; frame PNGs
    /// not included). A frame that finds the one before it done is short and the next one
    /// long, so frame rates are read over a second ([`windowed_fps`]).
    pub frame_ms: f64,
    /// What the frame-rate controller expected `frame_ms` to be, from the rate it measured
    /// before this frame; `None` where no target applies.
    pub predicted_ms: Option<f64>,
    /// Frame rate the controller aims for; `None` with a fixed budget, or with a method
    /// that shares no triangle budget.
    pub target_fps: Option<f64>,
}

/// One frame of a flight, as written to `flight.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRecord {
    pub frame: u64,
    /// Flight time: frame / fps.
    pub time_s: f64,
    /// Wall-clock seconds since the flight started.
    pub wall_s: f64,
    pub position_m: [f64; 3],
    /// Terrain height under the viewpoint (nearest sample of the resident current tile);
    /// `None` while that tile is not resident or the viewpoint is off the terrain.
    pub ground_m: Option<f64>,
    pub current: [i64; 2],
    /// Belt index of the farthest complete belt; `None` while the current tile is missing.
    pub farthest_complete_belt: Option<u32>,
    pub complete_belts: u32,
    pub resident_tiles: u64,
    /// Bytes the scene holds as the memory limit counts them ([`crate::scene::Scene::resident_bytes`]).
    pub resident_bytes: u64,
    pub memory_limit_bytes: u64,
    /// Bytes of the GPU allocations held for the terrain ([`crate::scene::Scene::gpu_bytes`]),
    /// part of `resident_bytes`.
    pub gpu_bytes: u64,
    /// The whole program's heap now ([`crate::process::heap_bytes`]): the terrain's CPU
    /// bytes and everything else the program allocated.
    pub heap_bytes: u64,
    /// wgpu's allocator report ([`crate::process::GpuReport`]): every GPU allocation, and
    /// those of the terrain; `None` without rendering or where the backend gives none.
    pub gpu_allocated: Option<crate::process::GpuReport>,
    /// The process's resident set now, when the OS reports it.
    pub rss_bytes: Option<u64>,
    /// Bytes of response bodies received so far (retries included).
    pub bytes_downloaded: u64,
    pub in_flight: u64,
    pub retries: u64,
    /// Downloaded bytes of tiles evicted before they were ever part of the complete square.
    pub evicted_unused_bytes: u64,
    /// Bytes the texture budget could spend on finer levels this frame.
    pub texture_budget_bytes: u64,
    pub render: Option<RenderRecord>,
}

impl FrameRecord {
    pub fn csv_row(&self) -> String {
        let render = match &self.render {
            None => ",,,,,,,,,,,,,".to_string(),
            Some(r) => format!(
                "{},{},{},{},{},{},{},{:.3},{:.3},{},{:.3},{},{:.2},{}",
                r.visible_tiles,
                r.triangles,
                r.triangles_needed,
                r.filler_triangles,
                r.draw_calls,
                r.global_budget,
                r.mask_levels
                    .iter()
                    .map(|(l, c)| format!("{l}:{c}"))
                    .collect::<Vec<_>>()
                    .join(";"),
                r.lod_ms,
                r.cpu_ms,
                r.gpu_ms.map_or(String::new(), |g| format!("{g:.3}")),
                r.frame_ms,
                r.predicted_ms.map_or(String::new(), |p| format!("{p:.3}")),
                1e3 / r.frame_ms.max(1e-6),
                r.target_fps.map_or(String::new(), |t| format!("{t}")),
            ),
        };
        format!(
            "{},{:.4},{:.4},{:.1},{:.1},{:.1},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            self.frame,
            self.time_s,
            self.wall_s,
            self.position_m[0],
            self.position_m[1],
            self.position_m[2],
            self.ground_m.map_or(String::new(), |g| format!("{g:.1}")),
            self.current[0],
            self.current[1],
            self.farthest_complete_belt
                .map_or(String::new(), |b| b.to_string()),
            self.complete_belts,
            self.resident_tiles,
            self.resident_bytes,
            self.memory_limit_bytes,
            self.gpu_bytes,
            self.heap_bytes,
            self.gpu_allocated
                .map_or(String::new(), |g| g.allocated.to_string()),
            self.gpu_allocated
                .map_or(String::new(), |g| g.terrain.to_string()),
            self.gpu_allocated
                .map_or(String::new(), |g| g.reserved.to_string()),
            self.rss_bytes.map_or(String::new(), |r| r.to_string()),
            self.bytes_downloaded,
            self.in_flight,
            self.retries,
            self.evicted_unused_bytes,
            self.texture_budget_bytes,
            render,
        )
    }
}

/// The obtained frame rate as a viewer shows it: frames drawn in the last second of
/// wall-clock time, at each rendered frame from the first full second on.
pub fn windowed_fps(records: &[FrameRecord]) -> Vec<(f64, f64)> {
    let rendered: Vec<f64> = records
        .iter()
        .filter(|r| r.render.is_some())
        .map(|r| r.wall_s)
        .collect();
    let mut start = 0;
    let mut out = Vec::new();
    for (i, &t) in rendered.iter().enumerate() {
        while rendered[start] <= t - 1.0 {
            start += 1;
        }
        if t >= 1.0 {
            out.push((t, (i + 1 - start) as f64));
        }
    }
    out
}
