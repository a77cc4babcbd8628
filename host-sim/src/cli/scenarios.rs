//! `harmonic-sim scenarios`: list the built-in scenarios.

use harmonic_sim::world::scenario::builtin_names;

/// Print the name of every built-in scenario, one a line.
pub fn run() {
    for name in builtin_names() {
        println!("{name}");
    }
}
