//! Which planner flies: the names `--planner` takes.

use std::fmt;
use std::str::FromStr;

/// The planners the simulator can fly.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum PlannerKind {
    /// The core's explorer with its default (screened, frontier-sourced) field, multigrid.
    Harmonic,
    /// The core's explorer with the seed's Laplace field, multigrid.
    HarmonicLaplace,
    /// The core's explorer with the seed's Laplace field and the seed paper's Gauss-Seidel.
    HarmonicGs,
    /// The core's explorer with the seed's Laplace field, solved the seed thesis's way
    /// ([`SolverKind::ThesisJacobi`](harmonic_core::explore::SolverKind::ThesisJacobi)). Selectable by name; not in [`PlannerKind::ALL`], so `all`
    /// and the default sweeps do not include it.
    HarmonicThesis,
    /// Closest frontier + A*.
    ClosestFrontier,
    /// Random frontier + A*.
    RandomFrontier,
    /// Information gain: most frontier voxels visible from a candidate pose.
    InfoGain,
    /// Information gain weighted by path length, g·exp(−λL).
    WeightedInfoGain,
}

impl PlannerKind {
    /// Every planner of the comparison, in the order tables list them (`all`). The
    /// thesis-faithful ablation [`PlannerKind::HarmonicThesis`] is left out: see
    /// [`PlannerKind::ABLATIONS`].
    pub const ALL: [PlannerKind; 7] = [
        PlannerKind::RandomFrontier,
        PlannerKind::ClosestFrontier,
        PlannerKind::InfoGain,
        PlannerKind::WeightedInfoGain,
        PlannerKind::HarmonicGs,
        PlannerKind::HarmonicLaplace,
        PlannerKind::Harmonic,
    ];

    /// Ablations `--planner` accepts by name but `all` leaves out.
    pub const ABLATIONS: [PlannerKind; 1] = [PlannerKind::HarmonicThesis];

    /// Every planner `--planner` accepts by name: [`PlannerKind::ALL`], then the ablations.
    pub fn named() -> impl Iterator<Item = PlannerKind> {
        Self::ALL.into_iter().chain(Self::ABLATIONS)
    }

    /// The name `--planner` takes.
    pub fn name(self) -> &'static str {
        match self {
            PlannerKind::Harmonic => "harmonic",
            PlannerKind::HarmonicLaplace => "harmonic-laplace",
            PlannerKind::HarmonicGs => "harmonic-gs",
            PlannerKind::HarmonicThesis => "harmonic-thesis",
            PlannerKind::ClosestFrontier => "closest-frontier",
            PlannerKind::RandomFrontier => "random-frontier",
            PlannerKind::InfoGain => "info-gain",
            PlannerKind::WeightedInfoGain => "weighted-info-gain",
        }
    }

    /// True for the core's explorer (any field, either solver).
    pub fn is_harmonic(self) -> bool {
        matches!(
            self,
            PlannerKind::Harmonic
                | PlannerKind::HarmonicLaplace
                | PlannerKind::HarmonicGs
                | PlannerKind::HarmonicThesis
        )
    }

    /// Parses `all` or a comma-separated list of names (duplicates removed, order kept).
    pub fn parse_list(s: &str) -> Result<Vec<PlannerKind>, String> {
        if s.trim() == "all" {
            return Ok(Self::ALL.to_vec());
        }
        let mut out = Vec::new();
        for part in s.split(',') {
            let k = part.trim().parse::<PlannerKind>()?;
            if !out.contains(&k) {
                out.push(k);
            }
        }
        Ok(out)
    }
}

impl fmt::Display for PlannerKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for PlannerKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::named().find(|k| k.name() == s).ok_or_else(|| {
            let names: Vec<&str> = Self::named().map(|k| k.name()).collect();
            format!("unknown planner `{s}` (expected one of {})", names.join(", "))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_thesis_ablation_is_named_but_not_in_all() {
        assert_eq!(
            "harmonic-thesis".parse::<PlannerKind>(),
            Ok(PlannerKind::HarmonicThesis)
        );
        assert!(!PlannerKind::ALL.contains(&PlannerKind::HarmonicThesis));
        assert!(PlannerKind::HarmonicThesis.is_harmonic());
        assert_eq!(PlannerKind::parse_list("all").unwrap(), PlannerKind::ALL.to_vec());
        for k in PlannerKind::named() {
            assert_eq!(k.name().parse::<PlannerKind>(), Ok(k));
        }
    }
}
