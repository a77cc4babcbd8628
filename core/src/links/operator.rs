//! Operator commands: what a ground station may ask of the explorer, and the state that leaves
//! it in.
//!
//! The commands arrive as MAVLink COMMAND_LONG (decoded by [`crate::links::mavlink::Bridge`], which
//! answers each with a COMMAND_ACK and reports the state in its HEARTBEAT's `custom_mode`):
//!
//! | command | MAVLink (`MAV_CMD_…`) | from | to |
//! |---|---|---|---|
//! | start | `MISSION_START` | waiting, paused, aborted, complete | exploring |
//! | pause (hold) | `DO_PAUSE_CONTINUE`, param1 = 0 | exploring | paused |
//! | resume | `DO_PAUSE_CONTINUE`, param1 = 1 | paused | exploring |
//! | abort (hold, stop planning) | `NAV_LOITER_UNLIM` | any | aborted |
//! | return home | `NAV_RETURN_TO_LAUNCH` | any but home | returning home |
//!
//! A command that makes no sense in the current state (resume while aborted, pause while
//! waiting) is denied and changes nothing; one that asks for the state the explorer is already
//! in is accepted and changes nothing. A pause while returning home resumes the return. Every
//! other command is answered as unsupported.
//!
//! [`OperatorState::Exploring`] plans the exploration and [`OperatorState::ReturningHome`] the
//! way home ([`crate::planning::explore::Explorer::plan_home`]), which ends in [`OperatorState::Home`]
//! (a hold, ready to land); in every other state the caller holds the vehicle where it is (and
//! keeps integrating depth, so the map stays current).

/// What the explorer is doing, as the operator sees it. The discriminant is the HEARTBEAT
/// `custom_mode` the bridge reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
#[repr(u32)]
pub enum OperatorState {
    /// Holding until the operator says start.
    Waiting = 0,
    /// Planning and flying to frontiers.
    Exploring = 1,
    /// Holding on the operator's word; resume continues.
    Paused = 2,
    /// Holding, planning stopped, until a new start.
    Aborted = 3,
    /// No reachable frontier is left; holding.
    Complete = 4,
    /// Flying back to where the exploration started.
    ReturningHome = 5,
    /// Home again: holding, ready to land.
    Home = 6,
}

impl OperatorState {
    /// The HEARTBEAT `custom_mode` of this state.
    pub fn custom_mode(self) -> u32 {
        self as u32
    }

    /// The state of a HEARTBEAT `custom_mode` (`None` for a value no state has).
    pub fn from_custom_mode(mode: u32) -> Option<Self> {
        [
            Self::Waiting,
            Self::Exploring,
            Self::Paused,
            Self::Aborted,
            Self::Complete,
            Self::ReturningHome,
            Self::Home,
        ]
        .into_iter()
        .find(|s| s.custom_mode() == mode)
    }

    /// Whether the explorer plans in this state (the exploration, or the way home).
    pub fn plans(self) -> bool {
        matches!(self, Self::Exploring | Self::ReturningHome)
    }

    /// A short lowercase name, for STATUSTEXTs and logs.
    pub fn name(self) -> &'static str {
        match self {
            Self::Waiting => "waiting",
            Self::Exploring => "exploring",
            Self::Paused => "paused",
            Self::Aborted => "aborted",
            Self::Complete => "complete",
            Self::ReturningHome => "returning home",
            Self::Home => "home",
        }
    }
}

/// An operator command the explorer knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub enum OperatorCommand {
    /// Start (or restart) exploring.
    Start,
    /// Hold where the vehicle is; keep the plan state for a resume.
    Pause,
    /// Continue after a pause.
    Resume,
    /// Hold and stop planning.
    Abort,
    /// Fly back to where the exploration started, through known free space.
    ReturnHome,
}

/// How the explorer answered a command (the COMMAND_ACK result).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub enum CommandResult {
    /// Done (or already so).
    Accepted,
    /// Known, but not in the current state; nothing changed.
    Denied,
    /// Not a command the explorer knows.
    Unsupported,
}

/// The operator state machine. See the [module documentation](self).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Operator {
    state: OperatorState,
    /// What a resume returns to: exploring, or returning home.
    resume_to: OperatorState,
}

impl Operator {
    /// Starts exploring at once, or waits for a start command if `wait_for_start`.
    pub const fn new(wait_for_start: bool) -> Self {
        Self {
            state: if wait_for_start {
                OperatorState::Waiting
            } else {
                OperatorState::Exploring
            },
            resume_to: OperatorState::Exploring,
        }
    }

    /// The current state.
    pub fn state(&self) -> OperatorState {
        self.state
    }

    /// Takes a command: the answer, and the new state if it changed.
    pub fn command(&mut self, command: OperatorCommand) -> (CommandResult, Option<OperatorState>) {
        use OperatorState as S;
        let to = match (command, self.state) {
            (OperatorCommand::Start, _) => S::Exploring,
            (OperatorCommand::Pause, S::Exploring | S::ReturningHome) => {
                self.resume_to = self.state;
                S::Paused
            }
            (OperatorCommand::Pause, S::Paused) => S::Paused,
            (OperatorCommand::Resume, S::Paused) => self.resume_to,
            (OperatorCommand::Resume, S::Exploring | S::ReturningHome) => self.state,
            (OperatorCommand::Abort, _) => S::Aborted,
            (OperatorCommand::ReturnHome, S::Home) => S::Home,
            (OperatorCommand::ReturnHome, _) => S::ReturningHome,
            (OperatorCommand::Pause | OperatorCommand::Resume, _) => return (CommandResult::Denied, None),
        };
        (CommandResult::Accepted, self.enter(to))
    }

    /// The way home ended at home: hold there (only while returning).
    pub fn arrived_home(&mut self) -> Option<OperatorState> {
        if self.state == OperatorState::ReturningHome {
            self.enter(OperatorState::Home)
        } else {
            None
        }
    }

    /// The explorer found no reachable frontier: complete (only while exploring).
    pub fn complete(&mut self) -> Option<OperatorState> {
        if self.state == OperatorState::Exploring {
            self.enter(OperatorState::Complete)
        } else {
            None
        }
    }

    fn enter(&mut self, to: OperatorState) -> Option<OperatorState> {
        (to != self.state).then(|| {
            self.state = to;
            to
        })
    }
}

impl Default for Operator {
    /// Exploring from the start, as the explorer always has.
    fn default() -> Self {
        Self::new(false)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use OperatorCommand as C;
    use OperatorState as S;

    #[test]
    fn start_pause_resume_abort_and_what_is_denied() {
        let mut op = Operator::new(true);
        assert_eq!(op.state(), S::Waiting);
        assert!(!op.state().plans());
        // Nothing to pause or resume before a start.
        assert_eq!(op.command(C::Pause), (CommandResult::Denied, None));
        assert_eq!(op.command(C::Resume), (CommandResult::Denied, None));
        assert_eq!(
            op.command(C::Start),
            (CommandResult::Accepted, Some(S::Exploring))
        );
        assert!(op.state().plans());
        assert_eq!(op.command(C::Pause), (CommandResult::Accepted, Some(S::Paused)));
        // Asking again is accepted and changes nothing.
        assert_eq!(op.command(C::Pause), (CommandResult::Accepted, None));
        assert_eq!(
            op.command(C::Resume),
            (CommandResult::Accepted, Some(S::Exploring))
        );
        assert_eq!(op.command(C::Resume), (CommandResult::Accepted, None));
        assert_eq!(op.command(C::Abort), (CommandResult::Accepted, Some(S::Aborted)));
        // An abort is not undone by a resume, only by a new start.
        assert_eq!(op.command(C::Resume), (CommandResult::Denied, None));
        assert_eq!(op.complete(), None);
        assert_eq!(
            op.command(C::Start),
            (CommandResult::Accepted, Some(S::Exploring))
        );
        assert_eq!(op.complete(), Some(S::Complete));
        assert_eq!(op.command(C::Pause), (CommandResult::Denied, None));
        assert_eq!(op.state().custom_mode(), 4);
        assert_eq!(Operator::default().state(), S::Exploring);
    }

    #[test]
    fn the_way_home_can_be_paused_and_ends_at_home() {
        let mut op = Operator::default();
        assert_eq!(op.arrived_home(), None);
        assert_eq!(
            op.command(C::ReturnHome),
            (CommandResult::Accepted, Some(S::ReturningHome))
        );
        assert!(op.state().plans());
        // A pause while returning resumes the return, not the exploration.
        assert_eq!(op.command(C::Pause), (CommandResult::Accepted, Some(S::Paused)));
        assert_eq!(
            op.command(C::Resume),
            (CommandResult::Accepted, Some(S::ReturningHome))
        );
        assert_eq!(op.complete(), None);
        assert_eq!(op.arrived_home(), Some(S::Home));
        assert!(!op.state().plans());
        assert_eq!(op.command(C::ReturnHome), (CommandResult::Accepted, None));
        assert_eq!(op.command(C::Resume), (CommandResult::Denied, None));
        // A new start explores again; a pause then resumes the exploration.
        assert_eq!(
            op.command(C::Start),
            (CommandResult::Accepted, Some(S::Exploring))
        );
        assert_eq!(op.command(C::Pause), (CommandResult::Accepted, Some(S::Paused)));
        assert_eq!(
            op.command(C::Resume),
            (CommandResult::Accepted, Some(S::Exploring))
        );
        assert_eq!(S::Home.custom_mode(), 6);
    }
}
