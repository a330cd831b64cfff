//! Every environment `hac` knows, by name: the continuous tasks of `hac-envs` (learned by the
//! neural agent) and the grid worlds of `hac-tabular` (learned by tabular HAC).

use anyhow::{Result, bail};
use hac_core::Env;

/// All environment names, continuous tasks first, in the order tools list them.
pub fn names() -> Vec<&'static str> {
    let mut names = hac_envs::names().to_vec();
    names.extend_from_slice(hac_tabular::names());
    names
}

/// Whether `name` is a grid world learned by the tabular learner (see [`crate::tabular_cmd`]).
pub fn is_tabular(name: &str) -> bool {
    hac_tabular::names().contains(&name)
}

/// A fresh environment by name; an unknown name is an error that lists the known ones.
pub fn make(name: &str) -> Result<Box<dyn Env>> {
    if let Ok(env) = hac_envs::make(name) {
        return Ok(env);
    }
    if let Ok(env) = hac_tabular::make(name) {
        return Ok(env);
    }
    bail!(
        "unknown environment `{name}` (known: {})",
        names().join(", ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_name_makes_its_environment() {
        for name in names() {
            assert_eq!(make(name).unwrap().spec().name, name);
        }
        assert!(is_tabular("four-rooms") && is_tabular("four-rooms-25"));
        assert!(!is_tabular("pendulum"));
        let err = make("acrobot").err().unwrap().to_string();
        assert!(
            err.contains("acrobot") && err.contains("pendulum") && err.contains("four-rooms-25"),
            "{err}"
        );
    }
}
