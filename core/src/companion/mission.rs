//! The mission's rules: what a fresh map is used for. A look-around first (turns on the spot),
//! then exploration, then the way home, or a hold on the operator's word. Every board follows
//! them: the companion ([`super::Companion`]) and the simulator's own run.

use core::f32::consts::{PI, TAU};

use nalgebra::Point3;

use crate::clock::Clock;
use crate::links::mavlink::wrap_angle;
use crate::links::operator::OperatorState;
use crate::mapping::map::VoxelIndex;
use crate::planning::explore::{Explorer, Fault, Goal, PlanOutcome, TargetChoice};

/// What the mission asks of a planner: explore from a pose, or plan the way home.
pub trait Planning<C: Clock> {
    /// Plans the exploration from `position`, heading `yaw` ([`Explorer::plan_timed`]).
    fn explore(&mut self, position: &Point3<f32>, yaw: f32, clock: &mut C) -> PlanOutcome;
    /// Plans the way to `home` ([`Explorer::plan_home`]).
    fn go_home(&mut self, position: &Point3<f32>, yaw: f32, home: &Point3<f32>, clock: &mut C)
        -> PlanOutcome;
}

impl<C: Clock, T: TargetChoice> Planning<C> for Explorer<'_, T> {
    fn explore(&mut self, position: &Point3<f32>, yaw: f32, clock: &mut C) -> PlanOutcome {
        self.plan_timed(position, yaw, clock)
    }
    fn go_home(
        &mut self,
        position: &Point3<f32>,
        yaw: f32,
        home: &Point3<f32>,
        clock: &mut C,
    ) -> PlanOutcome {
        self.plan_home(position, yaw, home, clock)
    }
}

/// What the mission does with a fresh map ([`Mission::step`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Step {
    /// A turn of the look-around: fly to this goal (the same position, the next heading). No
    /// plan is made.
    Look(Goal),
    /// The operator holds (waiting for start, paused, aborted): no plan is made.
    Held(OperatorState),
    /// A plan, as the explorer returned it; `home` if it is the way home.
    Plan {
        /// The explorer's outcome.
        outcome: PlanOutcome,
        /// True for the way home, false for exploration.
        home: bool,
    },
}

/// What a plan's outcome means for the mission ([`Mission::after`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum After {
    /// Go on: fly the goal, or hold on a fault.
    Continue,
    /// Explored; the way home starts with the next plan.
    Returning,
    /// Home again (the way home is complete).
    Home,
    /// Explored, and no way home is flown.
    Done,
}

/// The mission's state: home, the look-around's turns, whether the way home has begun.
#[derive(Debug, Clone)]
pub struct Mission {
    look_around: u32,
    return_home_after_complete: bool,
    home: Option<Point3<f32>>,
    looked: u32,
    returning: bool,
}

impl Mission {
    /// A mission that turns to `look_around` evenly spaced headings before its first plan (0 or
    /// 1: plans at once) and, if `return_home_after_complete`, flies home after a complete
    /// exploration. Home is where the first plan is made from, unless [`Mission::with_home`].
    pub fn new(look_around: u32, return_home_after_complete: bool) -> Self {
        Self {
            look_around,
            return_home_after_complete,
            home: None,
            looked: 0,
            returning: false,
        }
    }

    /// The mission with `home` set (a board that knows where the vehicle started).
    pub fn with_home(mut self, home: Point3<f32>) -> Self {
        self.home = Some(home);
        self
    }

    /// Where the way home goes, once known.
    pub fn home(&self) -> Option<Point3<f32>> {
        self.home
    }

    /// True if the next plan is the way home: after a complete exploration, or on the
    /// operator's word.
    pub fn going_home(&self, operator: OperatorState) -> bool {
        self.returning || operator == OperatorState::ReturningHome
    }

    /// Decides what to do from the vehicle at `position`, heading `yaw`, with the map the
    /// explorer holds now, and plans if that is what to do. The operator's hold comes first,
    /// then the look-around (while exploring), then a plan: the way home or exploration.
    pub fn step<C: Clock, P: Planning<C> + ?Sized>(
        &mut self,
        planner: &mut P,
        operator: OperatorState,
        position: Point3<f32>,
        yaw: f32,
        clock: &mut C,
    ) -> Step {
        let finite = position.coords.iter().all(|c| c.is_finite()) && yaw.is_finite();
        if self.home.is_none() && finite {
            self.home = Some(position);
        }
        if !operator.plans() {
            return Step::Held(operator);
        }
        let home = self.going_home(operator);
        if !home && finite && self.looked + 1 < self.look_around {
            self.looked += 1;
            return Step::Look(Goal {
                position,
                yaw: turned(yaw, self.look_around),
                frontier: VoxelIndex::new(0, 0, 0),
                escape: false,
            });
        }
        // Without a pose the explorer refuses the plan (BadPose) and counts it.
        let outcome = match (home, self.home) {
            (true, Some(at)) => planner.go_home(&position, yaw, &at, clock),
            (true, None) => PlanOutcome::Hold(Fault::HomeUnreachable),
            (false, _) => planner.explore(&position, yaw, clock),
        };
        Step::Plan { outcome, home }
    }

    /// What `outcome`, a plan of [`Step::Plan`] (`home` as it said), means for the mission;
    /// a complete exploration starts the way home if the mission flies one.
    pub fn after(&mut self, outcome: &PlanOutcome, home: bool) -> After {
        match outcome {
            PlanOutcome::Complete if home => After::Home,
            PlanOutcome::Complete if self.return_home_after_complete && self.home.is_some() => {
                self.returning = true;
                After::Returning
            }
            PlanOutcome::Complete => After::Done,
            _ => After::Continue,
        }
    }
}

/// `yaw` turned by a full turn over `n`, in [−π, π]. Within a turn of zero one addition or
/// subtraction of 2π brings it back, exactly (the simulator's runs were recorded with it);
/// anything farther is wrapped.
fn turned(yaw: f32, n: u32) -> f32 {
    let y = yaw + TAU / n.max(1) as f32;
    if y.abs() >= TAU || !y.is_finite() {
        wrap_angle(y)
    } else if y > PI {
        y - TAU
    } else if y < -PI {
        y + TAU
    } else {
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::NoClock;

    /// A planner that counts what it was asked and answers with `next`.
    struct Fake {
        explored: u32,
        homed: Option<Point3<f32>>,
        next: PlanOutcome,
    }

    impl Planning<NoClock> for Fake {
        fn explore(&mut self, _: &Point3<f32>, _: f32, _: &mut NoClock) -> PlanOutcome {
            self.explored += 1;
            self.next
        }
        fn go_home(&mut self, _: &Point3<f32>, _: f32, home: &Point3<f32>, _: &mut NoClock) -> PlanOutcome {
            self.homed = Some(*home);
            self.next
        }
    }

    fn fake(next: PlanOutcome) -> Fake {
        Fake {
            explored: 0,
            homed: None,
            next,
        }
    }

    const EXPLORING: OperatorState = OperatorState::Exploring;

    #[test]
    fn looks_around_on_the_spot_then_explores() {
        let mut m = Mission::new(4, true);
        let mut p = fake(PlanOutcome::Complete);
        let at = Point3::new(1.0, 2.0, 1.0);
        let mut yaw = 3.0;
        for turn in 0..3 {
            match m.step(&mut p, EXPLORING, at, yaw, &mut NoClock) {
                Step::Look(goal) => {
                    assert_eq!(goal.position, at, "turn {turn}");
                    let d = wrap_angle(goal.yaw - yaw);
                    assert!((d - TAU / 4.0).abs() < 1e-5, "turn {turn}: {d}");
                    assert!(goal.yaw > -PI && goal.yaw <= PI);
                    yaw = goal.yaw;
                }
                s => panic!("turn {turn}: {s:?}"),
            }
        }
        assert_eq!(p.explored, 0);
        assert!(matches!(
            m.step(&mut p, EXPLORING, at, yaw, &mut NoClock),
            Step::Plan { home: false, .. }
        ));
        assert_eq!(p.explored, 1);
        assert_eq!(m.home(), Some(at));
    }

    #[test]
    fn the_operator_holds_before_anything_else() {
        let mut m = Mission::new(4, true);
        let mut p = fake(PlanOutcome::Complete);
        for state in [
            OperatorState::Waiting,
            OperatorState::Paused,
            OperatorState::Aborted,
        ] {
            assert_eq!(
                m.step(&mut p, state, Point3::origin(), 0.0, &mut NoClock),
                Step::Held(state)
            );
        }
        assert_eq!(p.explored, 0);
        // Held steps are no turns of the look-around: all three are still to come.
        for _ in 0..3 {
            assert!(matches!(
                m.step(&mut p, EXPLORING, Point3::origin(), 0.0, &mut NoClock),
                Step::Look(_)
            ));
        }
    }

    #[test]
    fn a_complete_exploration_flies_home_then_ends_there() {
        let start = Point3::new(5.0, 5.0, 1.0);
        let mut m = Mission::new(0, true).with_home(start);
        let mut p = fake(PlanOutcome::Complete);
        let away = Point3::new(8.0, 1.0, 1.0);
        let Step::Plan { outcome, home } = m.step(&mut p, EXPLORING, away, 0.0, &mut NoClock) else {
            panic!("no plan");
        };
        assert!(!home);
        assert_eq!(m.after(&outcome, home), After::Returning);
        assert!(m.going_home(EXPLORING));
        let Step::Plan { outcome, home } = m.step(&mut p, EXPLORING, away, 0.0, &mut NoClock) else {
            panic!("no plan");
        };
        assert!(home);
        assert_eq!(p.homed, Some(start));
        assert_eq!(m.after(&outcome, home), After::Home);
    }

    #[test]
    fn without_a_way_home_a_complete_exploration_is_the_end() {
        let mut m = Mission::new(0, false);
        let mut p = fake(PlanOutcome::Complete);
        let Step::Plan { outcome, home } = m.step(&mut p, EXPLORING, Point3::origin(), 0.0, &mut NoClock)
        else {
            panic!("no plan");
        };
        assert_eq!(m.after(&outcome, home), After::Done);
        assert!(!m.going_home(EXPLORING));
        let hold = PlanOutcome::Hold(Fault::VehicleNotFree);
        assert_eq!(m.after(&hold, false), After::Continue);
    }

    #[test]
    fn the_operators_return_goes_home_and_without_a_home_holds() {
        // No plan yet and no pose: home is unknown.
        let mut m = Mission::new(0, true);
        let mut p = fake(PlanOutcome::Complete);
        let nowhere = Point3::new(f32::NAN, 0.0, 0.0);
        assert_eq!(
            m.step(&mut p, OperatorState::ReturningHome, nowhere, 0.0, &mut NoClock),
            Step::Plan {
                outcome: PlanOutcome::Hold(Fault::HomeUnreachable),
                home: true
            }
        );
        let at = Point3::new(1.0, 1.0, 1.0);
        assert!(matches!(
            m.step(&mut p, EXPLORING, at, 0.0, &mut NoClock),
            Step::Plan { home: false, .. }
        ));
        assert!(matches!(
            m.step(&mut p, OperatorState::ReturningHome, at, 0.0, &mut NoClock),
            Step::Plan { home: true, .. }
        ));
        assert_eq!(p.homed, Some(at));
    }

    #[test]
    fn turns_stay_in_range_and_match_one_subtraction() {
        for k in -40..=40 {
            let yaw = k as f32 * 0.08;
            let y = turned(yaw, 4);
            assert!((-PI..=PI).contains(&y), "{yaw} -> {y}");
            assert!(wrap_angle(y - yaw - TAU / 4.0).abs() < 1e-5);
        }
        assert!(turned(100.0, 4).abs() <= PI);
        assert!(turned(f32::NAN, 4).is_nan());
        assert_eq!(turned(3.0, 4), 3.0 + TAU / 4.0 - TAU);
    }
}
