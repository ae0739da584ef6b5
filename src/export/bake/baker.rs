//! The bake's folder: the `Baker` (its manifest, written or checked), the items' baked names, one
//! item's files written into the reference layout or a shard.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::tars::{complete_samples, OpenTar, TarOut};
use super::types::{ext_of, field_of, io_err, BakeError, BakeLayout, BakeReport, Shard, MEMBERS};
use crate::io::image::save_rgb_png;
use crate::mpi::npz::{save_npz_as, MpiDtype};
use crate::scene::stage::{SceneParts, SceneStage};
use crate::source::baked::{BakeManifest, BakedModel, FORMAT, MANIFEST};
use crate::source::Source;

/// A bake of one source through one scene stage into one folder.
pub struct Baker {
    pub(super) source: Arc<dyn Source>,
    pub(super) stage: Arc<SceneStage>,
    pub(super) out: PathBuf,
    pub(super) manifest: BakeManifest,
    pub(super) layout: BakeLayout,
    /// The element type of stored MPIs' colours and densities.
    pub(super) mpi_dtype: MpiDtype,
    /// [`baked_names`] of the source.
    pub(super) names: Vec<Result<String, String>>,
}

/// The models of a stage as the manifest records them.
pub fn stage_models(stage: &SceneStage) -> Vec<BakedModel> {
    let hex = |h: Option<u64>| h.map(|h| format!("{h:016x}"));
    let mut out = Vec::with_capacity(3);
    if let Some(d) = &stage.depth {
        out.push(BakedModel {
            role: "depth".into(),
            name: d.name(),
            content_hash: hex(d.content_hash()),
            identity: d.identity(),
        });
    }
    let m = &stage.mpi;
    out.push(BakedModel {
        role: "mpi".into(),
        name: m.name(),
        content_hash: hex(m.content_hash()),
        identity: m.identity(),
    });
    if let Some(s) = &stage.segmenter {
        out.push(BakedModel {
            role: "segment".into(),
            name: s.name(),
            content_hash: hex(s.content_hash()),
            identity: s.identity(),
        });
    }
    out
}

/// The name of item `id`'s files (the reference layout) or its key (WebDataset): the id with
/// every path separator made a `-` (ids of a folder of shards are `SHARD/KEY`), or why it cannot
/// name one.
fn baked_name(id: &str, layout: BakeLayout) -> Result<String, String> {
    let name = id.replace(['/', '\\'], "-");
    if name.is_empty() || name.starts_with('.') || name.contains('\0') {
        return Err(format!("the id `{id}` cannot name a file"));
    }
    if matches!(layout, BakeLayout::WebDataset { .. }) && name.contains('.') {
        return Err(format!("the id `{id}` has a `.`, which would end its WebDataset key"));
    }
    Ok(name)
}

/// Every item's [`baked_name`], over the whole source (so that every shard agrees): two ids of
/// one name are both refused.
fn baked_names(source: &dyn Source, layout: BakeLayout) -> Vec<Result<String, String>> {
    let mut names: Vec<Result<String, String>> = (0..source.len()).map(|i| baked_name(&source.id(i), layout)).collect();
    let mut first: std::collections::HashMap<String, usize> = std::collections::HashMap::new();
    let mut clash: Vec<(usize, usize)> = Vec::new();
    for (i, n) in names.iter().enumerate() {
        if let Ok(n) = n {
            match first.get(n) {
                Some(&j) => clash.push((i, j)),
                None => {
                    first.insert(n.clone(), i);
                }
            }
        }
    }
    for (i, j) in clash {
        let name = names[i].clone().unwrap_or_default();
        for (a, b) in [(i, j), (j, i)] {
            names[a] = Err(format!("the ids `{}` and `{}` both name `{name}`", source.id(a), source.id(b)));
        }
    }
    names
}

impl Baker {
    /// Prepares `out` for a bake of `source` through `stage` (`resize`: the size the source was
    /// opened with, recorded): creates the folders and writes `bake.json`, or checks that the
    /// one there is the same (same models, same source).
    pub fn new(
        source: Arc<dyn Source>,
        stage: Arc<SceneStage>,
        resize: Option<(usize, usize)>,
        out: &Path,
        layout: BakeLayout,
        mpi_dtype: MpiDtype,
    ) -> Result<Self, BakeError> {
        if layout == (BakeLayout::WebDataset { items_per_shard: 0 }) {
            return Err(BakeError::Mismatch("a WebDataset bake needs at least 1 item per shard".into()));
        }
        let network_mpi = stage.mpi.inference_runs().is_some();
        let mut members = vec!["images".to_string(), "disps".to_string(), "masks".to_string()];
        if network_mpi {
            members.push("mpis".into());
        }
        let manifest = BakeManifest {
            format: FORMAT.into(),
            source: source.describe(),
            source_fingerprint: format!("{:016x}", source.fingerprint()),
            resize: resize.map(|(w, h)| [w, h]),
            stage_fingerprint: format!("{:016x}", stage.config_fingerprint()),
            models: stage_models(&stage),
            members,
            mpi_dtype: network_mpi.then(|| mpi_dtype.as_str().to_string()),
            layout: layout.manifest_name(),
        };
        let subs: &[&str] = match layout {
            BakeLayout::WebDataset { .. } => &[],
            BakeLayout::Reference if network_mpi => &["images", "disps", "masks", "mpis"],
            BakeLayout::Reference => &["images", "disps", "masks"],
        };
        std::fs::create_dir_all(out).map_err(|e| io_err(out, e))?;
        match BakeManifest::read(out) {
            Ok(Some(old)) => {
                // the source's description names its path, which may differ between nodes
                let same = |m: &BakeManifest| {
                    let d = m.mpi_dtype.clone();
                    (m.source_fingerprint.clone(), m.stage_fingerprint.clone(), m.resize, m.layout.clone(), d)
                };
                if old.layout != manifest.layout {
                    let name = |l: &Option<String>| l.clone().unwrap_or_else(|| "reference".into());
                    return Err(BakeError::Mismatch(format!(
                        "{} is a {} bake; bake {} output into a new folder",
                        out.join(MANIFEST).display(),
                        name(&old.layout),
                        name(&manifest.layout)
                    )));
                }
                if old.mpi_dtype.is_some() && old.mpi_dtype != manifest.mpi_dtype {
                    return Err(BakeError::Mismatch(format!(
                        "{} stores MPIs as {}; bake with --mpi-dtype {} into a new folder",
                        out.join(MANIFEST).display(),
                        old.mpi_dtype.clone().unwrap_or_default(),
                        manifest.mpi_dtype.clone().unwrap_or_default()
                    )));
                }
                if same(&old) != same(&manifest) {
                    return Err(BakeError::Mismatch(format!(
                        "{} was baked from another source or with other models ({}); bake into a new folder",
                        out.join(MANIFEST).display(),
                        old.describe()
                    )));
                }
            }
            Ok(None) => {}
            Err(e) => return Err(BakeError::Mismatch(e.to_string())),
        }
        // only now: a refused folder is left as it was
        for sub in subs {
            std::fs::create_dir_all(out.join(sub)).map_err(|e| io_err(&out.join(sub), e))?;
        }
        let names = baked_names(source.as_ref(), layout);
        let baker = Baker { source, stage, out: out.to_path_buf(), manifest, layout, mpi_dtype, names };
        if !out.join(MANIFEST).is_file() {
            let tmp = baker.partial_dir(&Shard::ALL).join(format!("{MANIFEST}.{}", std::process::id()));
            std::fs::create_dir_all(tmp.parent().unwrap_or(out)).map_err(|e| io_err(&tmp, e))?;
            std::fs::write(&tmp, baker.manifest.to_bytes()).map_err(|e| io_err(&tmp, e))?;
            std::fs::rename(&tmp, out.join(MANIFEST)).map_err(|e| io_err(&out.join(MANIFEST), e))?;
        }
        Ok(baker)
    }

    pub fn manifest(&self) -> &BakeManifest {
        &self.manifest
    }

    /// The items of `shard`, in source order.
    pub fn items(&self, shard: &Shard) -> Vec<usize> {
        (0..self.source.len()).filter(|&i| shard.owns(&self.source.id(i))).collect()
    }

    pub(super) fn partial_dir(&self, shard: &Shard) -> PathBuf {
        self.out.join(".partial").join(shard.tag())
    }

    fn path(&self, sub: &str, id: &str, ext: &str) -> PathBuf {
        self.out.join(sub).join(format!("{id}.{ext}"))
    }

    /// Whether item `id` is baked in the reference layout: its image is there (written last) with
    /// its companions.
    pub fn is_done(&self, id: &str) -> bool {
        self.path("images", id, "png").is_file()
            && self.path("disps", id, "npy").is_file()
            && self.path("masks", id, "png").is_file()
            && (!self.manifest.has("mpis") || self.path("mpis", id, "npz").is_file())
    }

    /// Writes the baked files of one scene (the image last): into the reference layout, or as
    /// one sample of the open shard of `tars`.
    pub(super) fn write_scene(
        &self,
        shard: &Shard,
        scene: &SceneParts,
        tars: Option<&mut TarOut>,
    ) -> Result<(), BakeError> {
        let id = &scene.id;
        let d = &scene.disparity;
        let mut staged: Vec<(&str, PathBuf)> = Vec::with_capacity(4);
        let mut stage = |sub: &'static str, ext: &str, write: &dyn Fn(&Path) -> Result<(), String>| {
            let tmp = self.partial_dir(shard).join(format!("{}-{id}.{sub}.{ext}", std::process::id()));
            write(&tmp).map_err(|e| io_err(&tmp, e))?;
            staged.push((sub, tmp));
            Ok::<(), BakeError>(())
        };
        stage("disps", "npy", &|p| {
            crate::io::npy::write_f32(p, &[d.height as u64, d.width as u64], &d.data).map_err(|e| e.to_string())
        })?;
        stage("masks", "png", &|p| scene.masks.save_index_png(p).map_err(|e| e.to_string()))?;
        // an MPI is there only when it is stored: a network's (asked for below), or the item's own
        if let Some(mpi) = &scene.mpi {
            let mut mpi = (**mpi).clone();
            mpi.intrinsics = Some(scene.intrinsics);
            stage("mpis", "npz", &|p| {
                let write = || -> std::io::Result<()> {
                    let f = std::fs::File::create(p)?;
                    let w = save_npz_as(&mpi, std::io::BufWriter::new(f), self.mpi_dtype)?;
                    w.into_inner().map_err(std::io::IntoInnerError::into_error)?.sync_all()
                };
                write().map_err(|e| e.to_string())
            })?;
        }
        stage("images", "png", &|p| save_rgb_png(p, &scene.image).map_err(|e| e.to_string()))?;
        match tars {
            None => {
                for (sub, tmp) in staged {
                    if sub == "mpis" {
                        let dir = self.out.join("mpis");
                        std::fs::create_dir_all(&dir).map_err(|e| io_err(&dir, e))?;
                    }
                    let dest = self.path(sub, id, ext_of(sub));
                    std::fs::rename(&tmp, &dest).map_err(|e| io_err(&dest, e))?;
                }
                Ok(())
            }
            Some(t) => {
                let mut members = Vec::with_capacity(staged.len());
                for (sub, tmp) in staged {
                    let bytes = std::fs::read(&tmp).map_err(|e| io_err(&tmp, e))?;
                    std::fs::remove_file(&tmp).map_err(|e| io_err(&tmp, e))?;
                    members.push((field_of(sub).to_string(), bytes));
                }
                self.append_sample(shard, t, id, &members)
            }
        }
    }

    /// The fields every sample of a WebDataset bake has (the image last).
    fn fields(&self) -> Vec<&'static str> {
        MEMBERS.iter().filter(|m| m.0 != "mpis" || self.manifest.has("mpis")).map(|m| m.2).collect()
    }

    /// `bake-I-of-N-SSSSSS.tar`.
    fn tar_name(shard: &Shard, number: u64) -> String {
        format!("bake-{}-{number:06}.tar", shard.tag())
    }

    /// Appends a sample to the open shard (opening one first), finishing the shard when full.
    fn append_sample(
        &self,
        shard: &Shard,
        t: &mut TarOut,
        key: &str,
        members: &[(String, Vec<u8>)],
    ) -> Result<(), BakeError> {
        if t.open.is_none() {
            let name = Self::tar_name(shard, t.next);
            t.next += 1;
            t.open = Some(OpenTar::create(self.partial_dir(shard).join(&name), self.out.join(&name))?);
        }
        let open = t.open.as_mut().expect("opened above");
        open.append(key, members)?;
        t.done.insert(key.to_string());
        if open.items >= t.items_per_shard {
            t.open.take().expect("open").finish()?;
        }
        Ok(())
    }

    /// The WebDataset state at the start of a run of `shard`: the keys of every finished shard in
    /// the folder, this job's next shard number, and the complete samples of a shard a killed run
    /// of this job left in its partial folder, written out as a finished shard.
    pub(super) fn open_tars(&self, shard: &Shard, items_per_shard: usize) -> Result<TarOut, BakeError> {
        let mut t = TarOut { done: Default::default(), next: 0, open: None, items_per_shard };
        let prefix = format!("bake-{}-", shard.tag());
        let rd = std::fs::read_dir(&self.out).map_err(|e| io_err(&self.out, e))?;
        for ent in rd {
            let p = ent.map_err(|e| io_err(&self.out, e))?.path();
            let Some(name) = p.file_name().and_then(|n| n.to_str()).map(str::to_string) else { continue };
            if !name.ends_with(".tar") || !p.is_file() {
                continue;
            }
            if let Some(n) = name.strip_prefix(&prefix).and_then(|r| r.strip_suffix(".tar")) {
                if let Ok(n) = n.parse::<u64>() {
                    t.next = t.next.max(n + 1);
                }
            }
            let index = crate::source::shard::index_shard(&p).map_err(|e| io_err(&p, e))?;
            t.done.extend(index.samples.into_iter().map(|s| s.key));
        }
        let partial = self.partial_dir(shard);
        let mut leftovers: Vec<PathBuf> = match std::fs::read_dir(&partial) {
            Ok(rd) => rd
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|e| e == "tar"))
                .collect(),
            Err(_) => Vec::new(),
        };
        leftovers.sort();
        let fields = self.fields();
        let mut recovered = Vec::new();
        for p in &leftovers {
            let samples = complete_samples(p, &fields).map_err(|e| io_err(p, e))?;
            recovered.extend(samples.into_iter().filter(|(k, _)| !t.done.contains(k)));
        }
        if !recovered.is_empty() {
            let name = Self::tar_name(shard, t.next);
            t.next += 1;
            let tmp = self.out.join(".partial").join(format!("recovered-{}-{name}", std::process::id()));
            let mut open = OpenTar::create(tmp, self.out.join(&name))?;
            for (key, members) in &recovered {
                open.append(key, members)?;
                t.done.insert(key.clone());
            }
            open.finish()?;
        }
        Ok(t)
    }

    /// Where the report of `shard` goes: `bake-report.json` for the whole collection,
    /// `bake-report.I-of-N.json` for a shard.
    pub fn report_path(&self, shard: &Shard) -> PathBuf {
        if *shard == Shard::ALL {
            self.out.join("bake-report.json")
        } else {
            self.out.join(format!("bake-report.{}.json", shard.tag()))
        }
    }

    /// Writes the report (atomically).
    pub fn write_report(&self, shard: &Shard, report: &BakeReport) -> Result<PathBuf, BakeError> {
        let dest = self.report_path(shard);
        let tmp = self.out.join(".partial").join(format!("report-{}-{}", shard.tag(), std::process::id()));
        std::fs::create_dir_all(self.out.join(".partial")).map_err(|e| io_err(&tmp, e))?;
        let mut bytes = serde_json::to_vec_pretty(report).map_err(|e| io_err(&dest, e))?;
        bytes.push(b'\n');
        std::fs::write(&tmp, bytes).map_err(|e| io_err(&tmp, e))?;
        std::fs::rename(&tmp, &dest).map_err(|e| io_err(&dest, e))?;
        Ok(dest)
    }
}
