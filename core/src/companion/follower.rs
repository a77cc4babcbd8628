//! Following a plan one setpoint at a time: what a companion computer streams to an autopilot
//! that takes position setpoints, not trajectories.

use nalgebra::{Point3, Vector3};

use crate::planning::explore::Goal;
use crate::planning::streamline::{advance_radius, Waypoints};

/// Follows a plan's waypoints one setpoint at a time: the first waypoint the vehicle is not yet
/// within [`advance_radius`] of (less where the path turns, so corners are not cut), with the
/// heading of travel towards it, and at the last one the goal's yaw.
#[derive(Debug, Clone, Default)]
pub struct Follower {
    waypoints: Waypoints,
    next: usize,
    goal_yaw: f32,
    heading: Option<(usize, f32)>,
    turning: bool,
    active: bool,
}

impl Follower {
    /// Starts following `waypoints` to `goal` (only the goal if there are no waypoints; the
    /// waypoints past [`Waypoints`]' capacity are left out).
    pub fn follow(&mut self, waypoints: &[Point3<f32>], goal: &Goal) {
        self.waypoints.clear();
        for w in waypoints {
            if self.waypoints.push(*w).is_err() {
                break;
            }
        }
        if self.waypoints.is_empty() {
            let _ = self.waypoints.push(goal.position);
        }
        self.next = 0;
        self.goal_yaw = goal.yaw;
        self.heading = None;
        self.turning = false;
        self.active = true;
    }

    /// Stops following (the bridge holds).
    pub fn stop(&mut self) {
        self.active = false;
    }

    /// True while following a plan.
    pub fn is_active(&self) -> bool {
        self.active
    }

    /// True once the last waypoint is reached: the setpoint is then the goal's yaw on the spot.
    pub fn is_turning(&self) -> bool {
        self.turning
    }

    /// The setpoint for a vehicle at `position` with heading `yaw`, if following.
    pub fn setpoint(&mut self, position: &Point3<f32>, yaw: f32) -> Option<(Point3<f32>, f32)> {
        if !self.active {
            return None;
        }
        let len = self.waypoints.len();
        while self.next + 1 < len
            && self
                .waypoints
                .get(self.next)
                .is_some_and(|w| (w - position).norm() < advance_radius(&self.waypoints, self.next))
        {
            self.next += 1;
        }
        let target = self.waypoints.get(self.next).copied().unwrap_or(*position);
        if self.next + 1 >= len && (target - position).norm() < 1e-3 {
            self.turning = true;
        }
        let yaw = if self.turning {
            self.goal_yaw
        } else {
            match self.heading {
                Some((i, h)) if i == self.next => h,
                _ => {
                    let h = travel_heading(&(target - position)).unwrap_or(yaw);
                    self.heading = Some((self.next, h));
                    h
                }
            }
        };
        Some((target, yaw))
    }
}

/// Heading of travel along `seg` (radians about map z, 0 = +x), unless the segment is mostly
/// vertical: then `None`, and the caller keeps its yaw.
pub fn travel_heading(seg: &Vector3<f32>) -> Option<f32> {
    let horizontal = libm::sqrtf(seg.x * seg.x + seg.y * seg.y);
    (horizontal > 0.2 * seg.norm()).then(|| libm::atan2f(seg.y, seg.x))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn follower_walks_the_waypoints_then_turns_to_the_goal_yaw() {
        let mut f = Follower::default();
        let goal = Goal {
            position: Point3::new(2.0, 1.0, 1.0),
            yaw: 1.0,
            frontier: crate::mapping::map::VoxelIndex::new(0, 0, 0),
            escape: false,
        };
        let wps = [
            Point3::new(0.0, 0.0, 1.0),
            Point3::new(1.0, 0.0, 1.0),
            goal.position,
        ];
        f.follow(&wps, &goal);
        let (t, yaw) = f.setpoint(&Point3::new(0.0, 0.0, 1.0), 0.3).unwrap();
        assert_eq!(t, wps[1], "the vehicle stands on the first waypoint");
        assert!(yaw.abs() < 1e-6, "heading along +x");
        let (t, yaw) = f.setpoint(&Point3::new(1.0, 0.0, 1.0), 0.0).unwrap();
        assert_eq!(t, goal.position);
        assert!(
            (yaw - core::f32::consts::FRAC_PI_4).abs() < 1e-6,
            "heading to (2, 1)"
        );
        let (t, yaw) = f.setpoint(&goal.position, yaw).unwrap();
        assert_eq!((t, yaw), (goal.position, 1.0));
        f.stop();
        assert!(f.setpoint(&goal.position, 0.0).is_none());
    }

    #[test]
    fn a_vertical_segment_keeps_the_yaw() {
        assert_eq!(travel_heading(&Vector3::new(0.1, 0.0, 1.0)), None);
        assert_eq!(
            travel_heading(&Vector3::new(0.0, 1.0, 0.1)),
            Some(core::f32::consts::FRAC_PI_2)
        );
    }
}
