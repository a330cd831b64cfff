//! HAC on discrete grid worlds: the paper's four-rooms task and the tabular learner that solves
//! it with the same machinery as the continuous agent ("hierarchical Q-learning").
//!
//! - [`grid`]: the layout: cells, walls, one doorway per wall segment, rooms, moves.
//! - [`env`](mod@env): [`FourRooms`], the task as a [`hac_core::Env`] (cells as f32
//!   `[row, col]`, the move as one f32 index), with its budget and default hyperparameters.
//! - [`agent`]: [`TabularAgent`] (one Q table per level; the greedy [`hac_core::Policy`] and the
//!   Q-learning update) and [`TabularExploration`] (HAC's behaviour policy for discrete choices).
//! - [`learner`]: [`TabularHac`], which runs episodes through the unchanged core rollout, learns
//!   from their transitions and (by default, [`TabularConfig::all_segments`]) from every stretch
//!   of their path at the upper levels, and [`success_curve`], the mean learning curve of
//!   several trials.
//! - [`checkpoint`]: one level's Q table as a compact safetensors file (sparse, or coded
//!   against a palette of its values).
//! - This file: the registry ([`names`], [`make`], [`four_rooms`]).

#![forbid(unsafe_code)]

pub mod agent;
pub mod checkpoint;
pub mod env;
pub mod grid;
pub mod learner;

use hac_core::Env;

pub use agent::{
    InitialQ, LevelStats, TabularAgent, TabularConfig, TabularError, TabularExploration,
};
pub use checkpoint::TableFileError;
pub use env::FourRooms;
pub use grid::{Cell, Grid, GridError};
pub use learner::{CurveSpec, SuccessCurve, TabularHac, success_curve, success_curve_with};

/// Names accepted by [`make`] and [`four_rooms`], in the order tools should list them.
pub fn names() -> &'static [&'static str] {
    &[FourRooms::NAME, FourRooms::NAME_25]
}

/// The four-rooms task registered as `name`, as the concrete type the tabular learner needs.
pub fn four_rooms(name: &str) -> Result<FourRooms, UnknownEnv> {
    let size = match name {
        FourRooms::NAME => 10,
        FourRooms::NAME_25 => 25,
        _ => {
            return Err(UnknownEnv {
                name: name.to_string(),
            });
        }
    };
    Ok(FourRooms::new(size).expect("registered sizes hold four rooms"))
}

/// The environment registered as `name`, for tools that handle every environment alike.
pub fn make(name: &str) -> Result<Box<dyn Env>, UnknownEnv> {
    Ok(Box::new(four_rooms(name)?))
}

/// A name [`make`] does not know; the message lists the known ones.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown environment `{name}` (known: {})", names().join(", "))]
pub struct UnknownEnv {
    pub name: String,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registry_makes_every_listed_env_under_its_name() {
        for name in names() {
            assert_eq!(make(name).unwrap().spec().name, *name);
        }
        assert_eq!(four_rooms("four-rooms").unwrap().grid().size(), 10);
        assert_eq!(four_rooms("four-rooms-25").unwrap().grid().size(), 25);
        let err = make("five-rooms").unwrap_err();
        assert_eq!(
            err.to_string(),
            "unknown environment `five-rooms` (known: four-rooms, four-rooms-25)"
        );
    }
}
