//! The meshes both meshers make: the closed triangle mesh, how its top was meshed, and the
//! frame from the pixel lattice to the STL's coordinates.

use serde::{Deserialize, Serialize};

/// How the top surface was meshed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceKind {
    /// Exact flat terraces with vertical walls ([`super::terrace_mesh`]).
    Terraces,
    /// Error-bounded TIN through the pixel centres ([`super::heightfield_mesh`]).
    Heightfield,
}

impl SurfaceKind {
    pub(super) fn name(self) -> &'static str {
        match self {
            SurfaceKind::Terraces => "terraces",
            SurfaceKind::Heightfield => "heightfield",
        }
    }
}

/// A closed triangle mesh in metres, in the STL frame (`X = x`, `Y = -y`, `Z = height`).
/// Triangles are counter-clockwise seen from outside (outward normals).
#[derive(Debug, Clone)]
pub struct Mesh {
    pub(super) vertices: Vec<[f64; 3]>,
    pub(super) triangles: Vec<[u32; 3]>,
    pub(super) kind: SurfaceKind,
    pub(super) naive_triangles: u64,
    pub(super) max_height_error: f64,
    pub(super) max_lateral_deviation: f64,
    pub(super) chamfers: u64,
    pub(super) base_thickness: f64,
}

impl Mesh {
    /// Vertex positions, metres.
    pub fn vertices(&self) -> &[[f64; 3]] {
        &self.vertices
    }
    /// Triangles as vertex indices, counter-clockwise seen from outside.
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.triangles
    }
    /// How the top surface was meshed.
    pub fn kind(&self) -> SurfaceKind {
        self.kind
    }
    /// Triangles of the naive top mesh: two per pixel for terraces, two per cell between four
    /// pixel centres for a heightfield.
    pub fn naive_triangles(&self) -> u64 {
        self.naive_triangles
    }
    /// Largest |surface - sample| over all pixels, metres (0 for terraces).
    pub fn max_height_error(&self) -> f64 {
        self.max_height_error
    }
    /// Largest horizontal distance between the meshed outline of a region and the pixel
    /// edges, metres: the saddle chamfers of terraces, half a pitch for a heightfield (whose
    /// outline runs through the outermost pixel centres).
    pub fn max_lateral_deviation(&self) -> f64 {
        self.max_lateral_deviation
    }
    /// Number of saddle corners resolved by a chamfer (terraces only).
    pub fn chamfers(&self) -> u64 {
        self.chamfers
    }
    /// Thickness of the base below the lowest surface point, metres.
    pub fn base_thickness(&self) -> f64 {
        self.base_thickness
    }

    /// Enclosed volume, m^3, by the divergence theorem: the sum over triangles of
    /// `(a - o) . ((b - o) x (c - o)) / 6` (signed tetrahedra from a reference point `o`, here
    /// the first vertex, which keeps the sums small).
    pub fn volume(&self) -> f64 {
        let Some(o) = self.vertices.first() else { return 0.0 };
        let mut acc = 0.0;
        for t in &self.triangles {
            let [a, b, c] = t.map(|k| {
                let v = self.vertices[k as usize];
                [v[0] - o[0], v[1] - o[1], v[2] - o[2]]
            });
            acc += a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                + a[2] * (b[0] * c[1] - b[1] * c[0]);
        }
        acc / 6.0
    }

    /// Axis-aligned bounds `(min, max)`, metres.
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for v in &self.vertices {
            for k in 0..3 {
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
        (lo, hi)
    }

    /// Checks that the mesh is a closed, consistently oriented 2-manifold: no triangle repeats
    /// a vertex, every directed edge occurs exactly once and its reverse exactly once (so every
    /// edge joins exactly two triangles), and the triangles around each vertex form a single
    /// fan closing on itself (no pinched vertex). Returns a description of the first defect.
    pub fn check_closed(&self) -> std::result::Result<(), String> {
        let mut edges: Vec<(u32, u32)> = Vec::with_capacity(self.triangles.len() * 3);
        for (k, t) in self.triangles.iter().enumerate() {
            if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                return Err(format!("triangle {k} repeats a vertex: {t:?}"));
            }
            edges.extend([(t[0], t[1]), (t[1], t[2]), (t[2], t[0])]);
        }
        edges.sort_unstable();
        if let Some(w) = edges.windows(2).find(|w| w[0] == w[1]) {
            return Err(format!("directed edge {:?} is used twice", w[0]));
        }
        for &(a, b) in &edges {
            if edges.binary_search(&(b, a)).is_err() {
                return Err(format!("edge {:?} has no opposite (hole or T-junction)", (a, b)));
            }
        }
        drop(edges);
        // Link of each vertex v: triangle (v, b, c) maps b -> c; one single cycle required.
        let mut link: Vec<(u32, u32, u32)> = Vec::with_capacity(self.triangles.len() * 3);
        for t in &self.triangles {
            link.extend([(t[0], t[1], t[2]), (t[1], t[2], t[0]), (t[2], t[0], t[1])]);
        }
        link.sort_unstable();
        let mut start = 0;
        while start < link.len() {
            let v = link[start].0;
            let end = start + link[start..].partition_point(|e| e.0 == v);
            let fan = &link[start..end];
            let mut b = fan[0].1;
            for step in 1..=fan.len() {
                let k = fan
                    .binary_search_by_key(&b, |e| e.1)
                    .map_err(|_| format!("vertex {v}: its fan is open at vertex {b}"))?;
                b = fan[k].2;
                if b == fan[0].1 && step < fan.len() {
                    return Err(format!("vertex {v} is pinched: its triangles form several fans"));
                }
            }
            start = end;
        }
        Ok(())
    }
}

/// Geometry shared by both meshers: pixel-lattice coordinates to metres in the STL frame.
#[derive(Debug, Clone, Copy)]
pub(super) struct Frame {
    /// x of lattice column 0, metres.
    pub(super) x0: f64,
    /// y of lattice row 0, metres.
    pub(super) y0: f64,
    pub(super) px: f64,
    pub(super) py: f64,
}

impl Frame {
    /// Lattice `(col, row)` (fractional) -> STL `(X, Y)` in metres.
    pub(super) fn xy(&self, col: f64, row: f64) -> [f64; 2] {
        [self.x0 + col * self.px, -(self.y0 + row * self.py)]
    }
}
