//! Shape spaces of the built-in procedural families, built on first use and
//! cached as artefacts (the build is deterministic and takes about a second).

use super::space::{BuildOptions, BuildReport, NamedPoint, ShapeSpace, SpaceError, TrainingShape};
use crate::tools::{self, Category, Split};
use std::path::{Path, PathBuf};

/// Where the artefact of a category lives in `cache_dir`.
pub fn artefact_path(cache_dir: &Path, category: Category) -> PathBuf {
    cache_dir.join(format!("{}.gspace", category.name()))
}

/// Builds the space of a built-in category from its canonical and training instances.
pub fn build(
    category: Category,
    opts: &BuildOptions,
    progress: impl Fn(usize, usize) + Sync,
) -> Result<(ShapeSpace, BuildReport), SpaceError> {
    let family = tools::family(category)
        .map_err(|e| SpaceError::Artefact { path: category.name().into(), reason: e.to_string() })?;
    let canonical = family.iter().find(|i| i.split == Split::Canonical).ok_or_else(|| SpaceError::Artefact {
        path: category.name().into(),
        reason: "family has no canonical instance".into(),
    })?;
    let keypoints_of = |i: &tools::Instance| -> Vec<NamedPoint> {
        i.keypoints.iter().map(|k| NamedPoint { name: k.name.clone(), position: k.position }).collect()
    };
    let training: Vec<TrainingShape> = family
        .iter()
        .filter(|i| i.split == Split::Train)
        .map(|i| TrainingShape { name: i.name.clone(), mesh: i.mesh.clone(), keypoints: keypoints_of(i) })
        .collect();
    ShapeSpace::build(category.name(), &canonical.mesh, keypoints_of(canonical), &training, opts, progress)
}

/// Loads the cached artefact, or builds and caches it when it is missing,
/// corrupt or of another format version (the reason is logged).
pub fn load_or_build(
    category: Category,
    cache_dir: &Path,
    progress: impl Fn(usize, usize) + Sync,
) -> Result<ShapeSpace, SpaceError> {
    let path = artefact_path(cache_dir, category);
    match ShapeSpace::load(&path) {
        Ok(s) if s.build == BuildOptions::default() => return Ok(s),
        Ok(_) => tracing::info!("rebuilding {}: built with other options than this graspd's", path.display()),
        Err(e) if path.exists() => tracing::warn!("rebuilding: {e}"),
        Err(_) => tracing::info!("building the {} shape space (no artefact at {})", category.name(), path.display()),
    }
    let (space, report) = build(category, &BuildOptions::default(), progress)?;
    tracing::info!("built {} shape space: {} modes in {:.2} s", category.name(), report.modes, report.build_s);
    if let Err(e) = space.save(&path) {
        tracing::warn!("could not cache the shape space: {e}");
    }
    Ok(space)
}
