//! How far a map made with imperfect sensing is from the noise-free map of the same run.
//!
//! - [`MapAccuracy`]: the share of voxels whose state (unknown, free, occupied, uncertain)
//!   matches a reference map that integrated the noise-free depth of every scan of the same run
//!   at its true pose — the seed thesis's measure (Shade 2011, Fig. 6.19), over the whole grid
//!   and over the voxels either map observed. [`write_map_errors`] lists the voxels behind it
//!   (`explore --map-errors FILE`).

use harmonic_core::map::{Occupancy, VoxelMap};
use serde::Serialize;

/// How closely a map matches the noise-free map of the same run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct MapAccuracy {
    /// Share of all voxels in the same state (the thesis's measure).
    pub all_voxels: f64,
    /// Share of the voxels observed in either map that are in the same state.
    pub observed_voxels: f64,
    /// Voxels free in the reference but occupied in the map.
    pub false_occupied: usize,
    /// Voxels occupied in the reference but free in the map.
    pub false_free: usize,
    /// Voxels the reference observed and the map did not (unknown in the map only).
    pub unseen: usize,
    /// Voxels the map observed and the reference did not.
    pub seen_only_here: usize,
    /// [`MapAccuracy::false_occupied`] by where they lie: on a surface below them (a face
    /// neighbour below is occupied in the reference: floors, table tops), under one above
    /// (ceilings), beside one (walls; no occupied neighbour above or below), and away from
    /// every surface of the reference. Grown surfaces are the first three.
    pub false_occupied_where: [usize; 4],
    /// [`MapAccuracy::false_free`] by where they lie: under free space (a face neighbour
    /// above is free in the reference: floors, table tops), over it (ceilings), beside it
    /// (walls), and inside obstacles (no free face neighbour in the reference).
    pub false_free_where: [usize; 4],
}

/// Compares `map` with `reference` voxel by voxel (same grid).
pub fn accuracy(map: &VoxelMap<'_>, reference: &VoxelMap<'_>) -> MapAccuracy {
    use harmonic_core::map::Occupancy::{Free, Occupied};
    let n = map.dims().len();
    let (mut same, mut observed, mut same_observed, mut false_occupied, mut false_free) =
        (0usize, 0usize, 0usize, 0usize, 0usize);
    let (mut unseen, mut seen_only_here) = (0usize, 0usize);
    let (mut false_occupied_where, mut false_free_where) = ([0usize; 4], [0usize; 4]);
    let dims = map.dims();
    // Where voxel `i` lies against the reference's voxels in `state`: 0 if its face neighbour
    // `first` voxel up (+1) or down (−1) is in that state, 1 if the opposite one is, 2 if one
    // beside it is, 3 if none is.
    let beside = |i: usize, state, first: i32| -> usize {
        let v = dims.voxel(i);
        let is = |d: [i32; 3]| {
            dims.offset(v, d)
                .is_some_and(|n| reference.occupancy(dims.linear(n)) == state)
        };
        if is([0, 0, first]) {
            0
        } else if is([0, 0, -first]) {
            1
        } else if [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]].into_iter().any(is) {
            2
        } else {
            3
        }
    };
    for i in 0..n {
        let (a, b) = (map.occupancy(i), reference.occupancy(i));
        let seen = !(a == Occupancy::Unknown && b == Occupancy::Unknown);
        if a == b {
            same += 1;
            if seen {
                same_observed += 1;
            }
        }
        if seen {
            observed += 1;
        }
        match mismatch(a, b) {
            Some(VoxelError::FalseOccupied) => {
                false_occupied += 1;
                // On a surface below, under one above, beside one, away from all.
                false_occupied_where[beside(i, Occupied, -1)] += 1;
            }
            Some(VoxelError::FalseFree) => {
                false_free += 1;
                // Under free space, over it, beside it, inside an obstacle.
                false_free_where[beside(i, Free, 1)] += 1;
            }
            Some(VoxelError::Unseen) => unseen += 1,
            Some(VoxelError::SeenOnlyHere) => seen_only_here += 1,
            Some(VoxelError::Uncertain) | None => {}
        }
    }
    let frac = |a: usize, b: usize| if b == 0 { 1.0 } else { a as f64 / b as f64 };
    MapAccuracy {
        all_voxels: frac(same, n),
        observed_voxels: frac(same_observed, observed),
        false_occupied,
        false_free,
        unseen,
        seen_only_here,
        false_occupied_where,
        false_free_where,
    }
}

/// How one voxel of a map differs from the noise-free map of the same run ([`map_errors`]).
/// The first four are [`MapAccuracy`]'s counts; the fifth holds the remaining differences
/// (a voxel whose evidence cancels out, [`Occupancy::Uncertain`], in one map only).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VoxelError {
    /// Occupied here, free in the reference ([`MapAccuracy::false_occupied`]).
    FalseOccupied,
    /// Free here, occupied in the reference ([`MapAccuracy::false_free`]).
    FalseFree,
    /// Unknown here, observed in the reference ([`MapAccuracy::unseen`]).
    Unseen,
    /// Observed here, unknown in the reference ([`MapAccuracy::seen_only_here`]).
    SeenOnlyHere,
    /// Observed in both, uncertain in one of them.
    Uncertain,
}

impl VoxelError {
    /// The name written in the first column of [`write_map_errors`].
    pub fn name(self) -> &'static str {
        match self {
            VoxelError::FalseOccupied => "false_occupied",
            VoxelError::FalseFree => "false_free",
            VoxelError::Unseen => "unseen",
            VoxelError::SeenOnlyHere => "seen_only_here",
            VoxelError::Uncertain => "uncertain",
        }
    }
}

/// The name of an occupancy state in [`write_map_errors`].
fn state_name(o: Occupancy) -> &'static str {
    match o {
        Occupancy::Unknown => "unknown",
        Occupancy::Free => "free",
        Occupancy::Occupied => "occupied",
        Occupancy::Uncertain => "uncertain",
    }
}

/// How a voxel in state `a` in the map differs from the reference's `b`; `None` if it does
/// not. The one classification [`accuracy`] counts and [`map_errors`] lists.
fn mismatch(a: Occupancy, b: Occupancy) -> Option<VoxelError> {
    Some(match (a, b) {
        _ if a == b => return None,
        (Occupancy::Unknown, _) => VoxelError::Unseen,
        (_, Occupancy::Unknown) => VoxelError::SeenOnlyHere,
        (Occupancy::Occupied, Occupancy::Free) => VoxelError::FalseOccupied,
        (Occupancy::Free, Occupancy::Occupied) => VoxelError::FalseFree,
        _ => VoxelError::Uncertain,
    })
}

/// Every voxel whose state differs between `map` and `reference` (same grid), in storage
/// order, with how it differs. The voxels [`accuracy`] counts as not matching.
pub fn map_errors<'m>(
    map: &'m VoxelMap<'_>,
    reference: &'m VoxelMap<'_>,
) -> impl Iterator<Item = (usize, VoxelError)> + 'm {
    (0..map.dims().len())
        .filter_map(move |i| mismatch(map.occupancy(i), reference.occupancy(i)).map(|kind| (i, kind)))
}

/// Header of [`write_map_errors`]'s CSV.
pub const MAP_ERRORS_HEADER: &str =
    "error,ix,iy,iz,x_m,y_m,z_m,map,reference,log_odds,surface_mean_half_voxels,surface_weight";

/// Writes [`map_errors`] as CSV ([`MAP_ERRORS_HEADER`]), a line per voxel: how it differs, its
/// grid index, its centre in the map frame (metres), its state in each map, the map's
/// log-odds, and, where the map keeps a surface estimate with samples in that voxel
/// (`--stereo-model`), the estimate's mean distance of the voxel's centre in front of the
/// surface (half voxels: +1 in front of a surface on the voxel's far face) and the samples'
/// weight; both empty otherwise.
pub fn write_map_errors(
    map: &VoxelMap<'_>,
    reference: &VoxelMap<'_>,
    out: &mut impl std::io::Write,
) -> std::io::Result<()> {
    let geometry = map.geometry();
    let dims = map.dims();
    writeln!(out, "{MAP_ERRORS_HEADER}")?;
    for (i, kind) in map_errors(map, reference) {
        let v = dims.voxel(i);
        let c = geometry.center(v);
        let (mean, weight) = match harmonic_core::integrate::surface_estimate_at(map, i) {
            Some((m, w)) => (format!("{m:.3}"), format!("{w:.3}")),
            None => (String::new(), String::new()),
        };
        writeln!(
            out,
            "{},{},{},{},{:.3},{:.3},{:.3},{},{},{:.3},{mean},{weight}",
            kind.name(),
            v.x,
            v.y,
            v.z,
            c.x,
            c.y,
            c.z,
            state_name(map.occupancy(i)),
            state_name(reference.occupancy(i)),
            map.log_odds(i),
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use harmonic_core::map::{touched_words, Dims, LogOddsParams, MapGeometry};

    /// [`accuracy`] of a map against a reference over `dims`, each made of one frame's hits
    /// and misses (voxel indices).
    fn compare(
        dims: Dims,
        map_hits: &[usize],
        map_misses: &[usize],
        ref_hits: &[usize],
        ref_misses: &[usize],
    ) -> MapAccuracy {
        with_maps(dims, map_hits, map_misses, ref_hits, ref_misses, accuracy)
    }

    /// `f` of a map and a reference as [`compare`] makes them.
    fn with_maps<R>(
        dims: Dims,
        map_hits: &[usize],
        map_misses: &[usize],
        ref_hits: &[usize],
        ref_misses: &[usize],
        f: impl FnOnce(&VoxelMap<'_>, &VoxelMap<'_>) -> R,
    ) -> R {
        let g = MapGeometry::new(dims, nalgebra::Point3::origin(), 0.1).unwrap();
        let n = dims.len();
        let (mut lo_a, mut st_a) = (vec![0i8; n], vec![0u32; touched_words(&dims)]);
        let (mut lo_b, mut st_b) = (vec![0i8; n], vec![0u32; touched_words(&dims)]);
        let mut map = VoxelMap::new(g, LogOddsParams::default(), &mut lo_a, &mut st_a).unwrap();
        let mut reference = VoxelMap::new(g, LogOddsParams::default(), &mut lo_b, &mut st_b).unwrap();
        map.begin_frame();
        reference.begin_frame();
        for (m, hits, misses) in [
            (&mut map, map_hits, map_misses),
            (&mut reference, ref_hits, ref_misses),
        ] {
            for &i in hits {
                assert!(m.apply_hit(i));
            }
            for &i in misses {
                assert!(m.apply_miss(i));
            }
        }
        f(&map, &reference)
    }

    #[test]
    fn accuracy_counts_each_kind_of_mismatch() {
        // Voxel 0: free in both. 1: occupied in the reference, free in the map. 2: seen by the
        // reference only. 3: seen by the map only.
        let a = compare(Dims::new(4, 1, 1).unwrap(), &[3], &[0, 1], &[1, 2], &[0]);
        assert_eq!((a.false_free, a.false_occupied), (1, 0));
        assert_eq!((a.unseen, a.seen_only_here), (1, 1));
        assert_eq!(a.all_voxels, 0.25);
    }

    #[test]
    fn map_errors_list_every_mismatch_accuracy_counts() {
        // 3 × 1 × 4 voxels (x, z), index x + 3z. The reference: a floor (z = 0), free space
        // (z = 1), a ceiling (z = 2) and one voxel above it (x 1, z 3). The map: a voxel on the
        // floor (3, grown floor), the floor and the ceiling missed once each (1, 7), and two
        // voxels the reference never saw (9 occupied, 11 free). Everything else it did not see.
        let dims = Dims::new(3, 1, 4).unwrap();
        let (map_hits, map_misses) = ([3, 9], [1, 7, 11]);
        let (ref_hits, ref_misses) = ([0, 1, 2, 6, 7, 8, 10], [3, 4, 5]);
        let (a, csv) = with_maps(dims, &map_hits, &map_misses, &ref_hits, &ref_misses, |m, r| {
            let mut csv = Vec::new();
            write_map_errors(m, r, &mut csv).unwrap();
            (accuracy(m, r), String::from_utf8(csv).unwrap())
        });
        let mut lines = csv.lines();
        assert_eq!(lines.next(), Some(MAP_ERRORS_HEADER));
        let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
        let count = |kind: VoxelError| rows.iter().filter(|r| r.first() == Some(&kind.name())).count();
        let counts = [
            VoxelError::FalseOccupied,
            VoxelError::FalseFree,
            VoxelError::Unseen,
            VoxelError::SeenOnlyHere,
            VoxelError::Uncertain,
        ]
        .map(count);
        assert_eq!(
            counts,
            [a.false_occupied, a.false_free, a.unseen, a.seen_only_here, 0],
            "{a:?}"
        );
        assert_eq!(counts, [1, 2, 7, 2, 0]);
        // No voxel is in the same state in both: every one is listed, once, in storage order.
        assert_eq!(a.all_voxels, 0.0);
        assert_eq!(rows.len(), dims.len());
        assert!(rows
            .iter()
            .all(|r| r.len() == MAP_ERRORS_HEADER.split(',').count()));
        let row = |i: usize| rows.get(i).unwrap();
        assert_eq!(
            row(0)[..9],
            ["unseen", "0", "0", "0", "0.050", "0.050", "0.050", "unknown", "occupied"]
        );
        assert_eq!(row(0)[9], "0.000", "an unknown voxel's log-odds");
        // The grown floor, with the map's log-odds after one hit; no surface estimate
        // (exact-depth rules), so its two columns are empty.
        assert_eq!(
            row(3)[..9],
            [
                "false_occupied",
                "0",
                "0",
                "1",
                "0.050",
                "0.050",
                "0.150",
                "occupied",
                "free"
            ]
        );
        assert!(row(3)[9].parse::<f32>().unwrap() > 0.0);
        assert_eq!(row(3)[10..], ["", ""]);
        assert_eq!(row(7)[..3], ["false_free", "1", "0"]);
        assert_eq!(row(11)[..3], ["seen_only_here", "2", "0"]);
    }

    #[test]
    fn false_voxels_are_told_apart_by_the_surface_beside_them() {
        // 3 × 1 × 3 voxels (x, z): the reference has a floor (z = 0), free space (z = 1) and a
        // ceiling (z = 2). The map puts a voxel on the floor (grown floor), and misses one
        // voxel of the floor and one of the ceiling.
        let a = compare(
            Dims::new(3, 1, 3).unwrap(),
            &[3],
            &[1, 7],
            &[0, 1, 2, 6, 7, 8],
            &[3, 4, 5],
        );
        assert_eq!((a.false_occupied, a.false_free), (1, 2));
        assert_eq!(a.false_occupied_where, [1, 0, 0, 0], "on the floor");
        assert_eq!(
            a.false_free_where,
            [1, 1, 0, 0],
            "the floor under free space, the ceiling over it"
        );
    }
}
