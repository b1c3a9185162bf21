//! The in-core diamond DAG: the diamonds from the root down to the current cut, each with
//! its reconstructed vertex grid.
//!
//! A diamond is two triangles (halves) that lie in its two parents. As soon as one parent
//! is refined, the half inside it is known (cut from that parent's refined lattice) and
//! can be drawn; the diamond itself can be refined only once both halves are present,
//! that is when all its parents are refined (the 4-8 rule that keeps every cut free of
//! cracks and T-junctions). The cut is the set of present halves of unrefined diamonds.

use std::collections::{HashMap, HashSet};
use std::hash::BuildHasherDefault;
use std::sync::Arc;

use quincunx_decoder::diamond::PlanarId;
use quincunx_decoder::incremental::{Details, PlanarRefiner, Refined};
use quincunx_decoder::lifting::DiamondMask;

use crate::colour::{CHANNELS, ColourDetails, ColourLayer, ColourNode};
pub use crate::domain::Half;
use crate::domain::{Domain, World};
pub use crate::open::DagError;
use quincunx_decoder::entropy::class_bound;

pub use quincunx_decoder::diamond::{IdHasher, IdMap};

/// One drawable triangle of the cut: a present half of an unrefined diamond.
#[derive(Clone, Debug)]
pub struct Patch<I = PlanarId> {
    /// The diamond.
    pub id: I,
    /// Which half.
    pub half: Half,
    /// The diamond's frame `[E1, P1, E2, P2]` (id units; planar `z = 0`): on the plane,
    /// grid vertex `(i, j)` is at `E1 + (i (P1 - E1) + j (P2 - E1)) / N`; on a planet
    /// [`Domain::vertex_world`] places vertices (halves fold across cube edges).
    pub corners: [[i64; 3]; 4],
    /// The diamond's `(N+1)^2` vertex grid (integer samples; metres through the world
    /// mapping). Shared, not copied.
    pub grid: Arc<Vec<i32>>,
    /// Changes whenever the grid or the halves change: a renderer re-uploads a patch
    /// only when `(id, half, generation)` is new to it.
    pub generation: u64,
    /// With a colour layer: the diamond's `(Nc+1)^2` Y, Co, Cg grids (YCoCg-R integers;
    /// [`ColourLayer::rgb`] turns a vertex into sRGB), laid out on the same frame.
    pub colour: Option<Arc<Vec<Vec<i32>>>>,
}

/// What entered and left the cut since the previous `Session::cut_changes`.
#[derive(Clone, Debug)]
pub struct PatchChanges<I = PlanarId> {
    /// Patches that entered the cut, in a stable order.
    pub entered: Vec<Patch<I>>,
    /// Halves that left it.
    pub left: Vec<(I, Half)>,
}

/// A diamond in the DAG.
#[derive(Clone, Debug)]
pub struct Node<I = PlanarId> {
    /// The diamond.
    pub id: I,
    /// Its `(N+1)^2` vertex grid; entries of absent halves are 0.
    pub grid: Arc<Vec<i32>>,
    /// Which halves are present (index by [`Half`]).
    pub present: [bool; 2],
    /// Which halves exist at all (a border diamond has one; a half inside a parent that
    /// lies outside the raster never arrives).
    pub expected: [bool; 2],
    /// Its refinement while it is refined: side information only; the lattice is
    /// dropped once its children have their halves (it would only be read to rebuild
    /// them, and their halves never change while it stays refined).
    pub refined: Option<Refined<I>>,
    /// The side-information class its first parent's blob carries for it: a bound on how
    /// far its finer surface departs from its grid (`None` until known).
    pub class: Option<u8>,
    /// The class of its error bound for the geometric metric: [`Node::class`] once known,
    /// and until then (or where no blob carries one: children of a diamond without a
    /// blob) the smallest class of a refined parent's bound, which bounds it too (a
    /// parent's bound is at least its children's), or the first class of a refined
    /// parent's [`Node::bound_profile`]. `None` for the roots.
    pub bound_class: Option<u8>,
    /// Where no blob below it will carry its descendants' bounds (nothing below it has
    /// one): per level below it, from its children down, a class bounding every
    /// descendant of that level (its owner's blob's profile, or the rest of a refined
    /// parent's; the smaller of two).
    pub bound_profile: Option<Arc<[u8]>>,
    /// Smallest and largest grid value over its present halves.
    pub z_range: (i32, i32),
    /// Its frame corners `[E1, P1, E2, P2]` (id units; planar `z = 0`, planets: points
    /// on the cube surface).
    pub corners: [[i64; 3]; 4],
    /// Its children inside the data (empty for the finest diamonds).
    pub children: Arc<[I]>,
    /// Changes whenever its grid or halves change (a DAG-wide counter), so cached
    /// judgements about it can tell they are stale.
    pub generation: u64,
    /// Its colour (with a colour layer, where the colour repository covers it).
    pub colour: Option<ColourNode<I>>,
}

impl<I> Node<I> {
    /// Whether every half that exists is present.
    pub fn complete(&self) -> bool {
        self.present
            .iter()
            .zip(&self.expected)
            .all(|(p, e)| *p || !*e)
    }

    /// Whether a half is present.
    pub fn has(&self, half: Half) -> bool {
        self.present[half.index()]
    }

    /// The side-information bound on how far its subtree departs from its grid (metres;
    /// 0 while unknown).
    pub fn bound_m(&self, world: &impl World) -> f64 {
        self.class
            .map_or(0.0, |k| class_bound(k) as f64 * world.value_scale_m().abs())
    }

    /// Lowest and highest height (metres) of its own surface and of the full-resolution
    /// surface beneath it: its grid's range widened by [`Node::bound_m`].
    pub fn height_bounds_m(&self, world: &impl World) -> (f64, f64) {
        let bound = self.bound_m(world);
        let (a, b) = (
            world.height_m(self.z_range.0),
            world.height_m(self.z_range.1),
        );
        (a.min(b) - bound, a.max(b) + bound)
    }
}

/// The DAG of one repository (planar unless `R` says otherwise).
#[derive(Debug)]
pub struct Dag<R: Domain = PlanarRefiner> {
    refiner: Arc<R>,
    colour: Option<Arc<ColourLayer<R>>>,
    nodes: IdMap<Node<R::Id>, R::Id>,
    generations: u64,
    /// Diamonds holding a refined lattice.
    refined: usize,
    /// Halves in the cut, kept by every refinement and coarsening.
    cut_halves: usize,
    /// Refinements and coarsenings so far.
    changes: u64,
    /// Diamonds whose halves may have entered or left the cut since the last
    /// [`Dag::take_cut_changes`].
    touched: HashSet<R::Id, BuildHasherDefault<IdHasher>>,
    /// The halves [`Dag::take_cut_changes`] has reported in the cut.
    reported: HashSet<(R::Id, Half), BuildHasherDefault<IdHasher>>,
}

/// How the cut changed since the previous [`Dag::take_cut_changes`]: what a retained-mode
/// renderer uploads and frees. A half's grid entries never change while it is in the cut
/// (a half is written once when its parent refines and cleared when it leaves; adding or
/// clearing the other half leaves its entries alone), so membership is all that changes.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CutChanges<I> {
    /// Halves that entered the cut, sorted.
    pub entered: Vec<(I, Half)>,
    /// Halves that left it, sorted.
    pub left: Vec<(I, Half)>,
}

impl<I> CutChanges<I> {
    /// Whether nothing changed.
    pub fn is_empty(&self) -> bool {
        self.entered.is_empty() && self.left.is_empty()
    }
}

impl<R: Domain> Dag<R> {
    /// A DAG holding the roots (complete, from the repository's root grids).
    pub fn new(refiner: Arc<R>) -> Dag<R> {
        Dag::with_colour(refiner, None)
    }

    /// A DAG of elevation and, optionally, a colour layer matched to it
    /// ([`ColourLayer::match_to`]): every diamond then carries both.
    pub fn with_colour(refiner: Arc<R>, colour: Option<Arc<ColourLayer<R>>>) -> Dag<R> {
        let n = refiner.n();
        let nodes = refiner
            .roots()
            .into_iter()
            .map(|(root, grid)| {
                let node = Node {
                    id: root,
                    corners: refiner.corners(root),
                    children: refiner.children(root).unwrap_or_default().into(),
                    z_range: z_range(grid, n, [true, true]),
                    generation: 0,
                    grid: Arc::new(grid.to_vec()),
                    present: [true, true],
                    expected: [true, true],
                    refined: None,
                    class: None,
                    bound_class: None,
                    bound_profile: None,
                    colour: colour.as_ref().and_then(|c| c.root_grids(root)),
                };
                (root, node)
            })
            .collect::<IdMap<_, _>>();
        let touched = nodes.keys().copied().collect();
        let cut_halves = 2 * nodes.len();
        Dag {
            nodes,
            refiner,
            colour,
            generations: 1,
            refined: 0,
            cut_halves,
            changes: 0,
            touched,
            reported: HashSet::default(),
        }
    }

    /// The colour layer, if any.
    pub fn colour(&self) -> Option<&ColourLayer<R>> {
        self.colour.as_deref()
    }

    /// Colour texels per elevation grid step (`Nc / Ne`; 0 without colour): the mean
    /// projected texel size is the edge length divided by it.
    pub fn texels_per_edge(&self) -> f64 {
        self.colour
            .as_ref()
            .map_or(0.0, |c| c.n() as f64 / self.refiner.n() as f64)
    }

    /// The colour id whose blob refining `id` needs (`None`: no colour layer, or its
    /// colour is procedural or outside the colour data).
    pub fn colour_blob_id(&self, id: R::Id) -> Option<R::Id> {
        let layer = self.colour.as_ref()?;
        let node = self.nodes.get(&id)?;
        let colour = node.colour.as_ref()?;
        layer.is_coded(colour.id).then_some(colour.id)
    }

    /// The incremental decoder this DAG refines with.
    pub fn refiner(&self) -> &R {
        &self.refiner
    }

    /// A diamond, if it is in the DAG.
    pub fn node(&self, id: R::Id) -> Option<&Node<R::Id>> {
        self.nodes.get(&id)
    }

    /// Every diamond in the DAG.
    pub fn nodes(&self) -> impl Iterator<Item = &Node<R::Id>> {
        self.nodes.values()
    }

    /// Diamonds in the DAG.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    /// Whether nothing is held (never: the roots stay).
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Bytes of grids and nodes held (constant time: every grid is `(N+1)^2` values;
    /// lattices live only while a refinement hands its children their halves).
    pub fn memory_bytes(&self) -> usize {
        let per_node = |n: usize| self.nodes.len() * 4 * (n + 1) * (n + 1);
        // Every node holds colour grids once a colour layer exists (estimate: the few
        // outside the colour data hold none). Lattices are not kept.
        let colour = self
            .colour
            .as_ref()
            .map_or(0, |c| CHANNELS * per_node(c.n()));
        self.nodes.len() * Self::node_bytes(self.refiner.n()) + colour
    }

    /// Bytes a refinement adds at most: its transient lattice and up to four children's
    /// nodes, in every layer.
    pub fn refinement_bytes(&self) -> usize {
        let n = self.refiner.n();
        let colour = self.colour.as_ref().map_or(0, |c| {
            let nc = c.n();
            CHANNELS * (Self::lattice_bytes(nc) + 4 * 4 * (nc + 1) * (nc + 1))
        });
        Self::lattice_bytes(n) + 4 * Self::node_bytes(n) + colour
    }

    /// Bytes one node holds (its grid and the node itself).
    pub fn node_bytes(n: usize) -> usize {
        4 * (n + 1) * (n + 1) + std::mem::size_of::<Node<R::Id>>()
    }

    /// Bytes one refined lattice adds.
    pub fn lattice_bytes(n: usize) -> usize {
        4 * ((n + 1) * (n + 1) + n * n)
    }

    /// Diamonds holding a refined lattice.
    pub fn refined_len(&self) -> usize {
        self.refined
    }

    /// Whether `id` can be refined now: present, complete, unrefined and carrying details.
    pub fn is_refinable(&self, id: R::Id) -> bool {
        self.nodes
            .get(&id)
            .is_some_and(|n| n.complete() && n.refined.is_none())
            && self.refiner.is_refinable(id)
    }

    /// Whether `id` can be coarsened now: refined, and none of its children refined.
    pub fn is_coarsenable(&self, id: R::Id) -> bool {
        self.nodes.get(&id).is_some_and(|n| n.refined.is_some())
            && self
                .children(id)
                .iter()
                .all(|c| self.nodes.get(c).is_none_or(|n| n.refined.is_none()))
    }

    /// The children of `id` that the repository holds (inside the data).
    pub fn children(&self, id: R::Id) -> Arc<[R::Id]> {
        match self.nodes.get(&id) {
            Some(node) => node.children.clone(),
            None => self.refiner.children(id).unwrap_or_default().into(),
        }
    }

    /// The parents of `id` (one for planar border half diamonds, none for roots).
    pub fn parents(&self, id: R::Id) -> Vec<R::Id> {
        self.refiner.parents(id)
    }

    /// Refines `id` with its decoded details (`None`: no blob): synthesises its lattice
    /// and gives each child the half that lies in it. Returns the children.
    pub fn refine(
        &mut self,
        id: R::Id,
        details: Option<&Details<R::Id>>,
    ) -> Result<Vec<R::Id>, DagError> {
        self.refine_layers(id, details, None)
    }

    /// [`Dag::refine`] with the colour's details too (`None`: zero or procedural; ignored
    /// without a colour layer).
    pub fn refine_layers(
        &mut self,
        id: R::Id,
        details: Option<&Details<R::Id>>,
        colour: Option<&ColourDetails<R::Id>>,
    ) -> Result<Vec<R::Id>, DagError> {
        self.counting_cut(id, |dag| dag.refine_uncounted(id, details, colour))
    }

    /// Runs `op` on `id` and keeps the cut's count: an operation on `id` changes the cut
    /// only at `id` and its children.
    fn counting_cut<T>(&mut self, id: R::Id, op: impl FnOnce(&mut Self) -> T) -> T {
        let near = |dag: &Self| -> usize {
            let halves = |id: R::Id| Half::BOTH.iter().filter(|&&h| dag.in_cut(id, h)).count();
            halves(id) + dag.children(id).iter().map(|&c| halves(c)).sum::<usize>()
        };
        let before = near(self);
        let out = op(self);
        self.cut_halves = (self.cut_halves + near(self)).saturating_sub(before);
        self.changes += 1;
        out
    }

    /// [`Dag::refine_layers`] without the cut's count.
    fn refine_uncounted(
        &mut self,
        id: R::Id,
        details: Option<&Details<R::Id>>,
        colour: Option<&ColourDetails<R::Id>>,
    ) -> Result<Vec<R::Id>, DagError> {
        let not_refinable = || DagError::NotRefinable(format!("{id:?}"));
        if !self.is_refinable(id) {
            return Err(not_refinable());
        }
        let node = self.nodes.get(&id).ok_or_else(not_refinable)?;
        let refined = self.refiner.synthesize(id, &node.grid, details)?;
        let colour_refined = match (&self.colour, &node.colour) {
            (Some(layer), Some(c)) if layer.is_refinable(c.id) => {
                if colour.is_some_and(|d| d.id != c.id) {
                    return Err(not_refinable());
                }
                Some(layer.synthesize(c, colour)?)
            }
            _ => None,
        };
        let classes: HashMap<R::Id, u8> = refined.child_classes.iter().copied().collect();
        let profiles: HashMap<R::Id, Arc<[u8]>> = refined
            .child_profiles
            .iter()
            .filter(|(_, p)| !p.is_empty())
            .map(|(c, p)| (*c, Arc::from(p.as_slice())))
            .collect();
        let inherited = node.bound_class;
        // This diamond's profile, one level on: its children's class and theirs.
        let handed = node
            .bound_profile
            .as_ref()
            .and_then(|p| Some((*p.first()?, Arc::<[u8]>::from(&p[1..]))));
        let children = self.children(id);
        // Each child gets the half that lies in this diamond, from its fresh lattices.
        for &child in children.iter() {
            self.add_half(child, &refined, colour_refined.as_deref())?;
            if let Some(node) = self.nodes.get_mut(&child) {
                let class = classes.get(&child).copied();
                if class.is_some() {
                    node.class = class;
                }
                node.bound_class = [
                    node.bound_class,
                    class,
                    inherited,
                    handed.as_ref().map(|h| h.0),
                ]
                .into_iter()
                .flatten()
                .min();
                for p in [profiles.get(&child), handed.as_ref().map(|h| &h.1)]
                    .into_iter()
                    .flatten()
                {
                    node.bound_profile = Some(tighter_profile(node.bound_profile.take(), p));
                }
            }
        }
        // The lattices are not kept: a child's half never changes while this diamond
        // stays refined, and coarsening only clears it.
        self.touched.insert(id);
        if let Some(node) = self.nodes.get_mut(&id) {
            node.refined = Some(without_lattice(refined));
            if let Some(c) = node.colour.as_mut() {
                c.refined = colour_refined.map(|ls| ls.into_iter().map(without_lattice).collect());
            }
            self.refined += 1;
        }
        Ok(children.to_vec())
    }

    /// Coarsens `id`: drops its refinement and the halves of its children that lay in it
    /// (children left with no half leave the DAG).
    pub fn coarsen(&mut self, id: R::Id) -> Result<(), DagError> {
        if !self.is_coarsenable(id) {
            return Err(DagError::NotCoarsenable(format!("{id:?}")));
        }
        self.counting_cut(id, |dag| dag.coarsen_uncounted(id));
        Ok(())
    }

    /// [`Dag::coarsen`] of a coarsenable diamond, without the cut's count.
    fn coarsen_uncounted(&mut self, id: R::Id) {
        self.touched.insert(id);
        if let Some(node) = self.nodes.get_mut(&id) {
            node.refined = None;
            if let Some(c) = node.colour.as_mut() {
                c.refined = None;
            }
            self.refined -= 1;
        }
        for &child in self.children(id).iter() {
            self.remove_half(child, id);
        }
    }

    /// Writes the half of `child` that lies in `parent` (its fresh lattice, and its colour
    /// lattices) into the child's grids, creating the child if it is new.
    fn add_half(
        &mut self,
        child: R::Id,
        parent: &Refined<R::Id>,
        colour: Option<&[Refined<R::Id>]>,
    ) -> Result<(), DagError> {
        let side_parents = self.refiner.side_parents(child);
        let Some(h) = side_parents.iter().position(|&p| p == parent.id) else {
            return Err(DagError::NotRefinable(format!(
                "{:?} is not a side parent of {child:?}",
                parent.id
            )));
        };
        let (half, written) = self.refiner.partial_child_grid(child, &[parent])?;
        let colour_half = match (&self.colour, colour) {
            (Some(layer), Some(lattices)) => match layer.colour_id(child) {
                Some(c) => Some(layer.child_half(c, lattices)?),
                None => None,
            },
            _ => None,
        };
        let merge = |grid: &mut [i32], half: &[i32], written: &[bool]| {
            for ((g, v), w) in grid.iter_mut().zip(half).zip(written) {
                if *w {
                    *g = *v;
                }
            }
        };
        let node = match self.nodes.remove(&child) {
            Some(mut node) => {
                merge(
                    Arc::make_mut(&mut node.grid).as_mut_slice(),
                    &half,
                    &written,
                );
                node.present[h] = true;
                node.colour = match (node.colour.take(), colour_half) {
                    (Some(mut c), Some((grids, written))) => {
                        for (g, v) in Arc::make_mut(&mut c.grids).iter_mut().zip(&grids) {
                            merge(g, v, &written);
                        }
                        Some(c)
                    }
                    (None, Some((grids, _))) => layer_node(self.colour.as_deref(), child, grids),
                    (c, None) => c,
                };
                node
            }
            None => {
                let parents = self.parents(child);
                let mut present = [false; 2];
                present[h] = true;
                Node {
                    id: child,
                    generation: 0,
                    corners: self.refiner.corners(child),
                    children: self.refiner.children(child).unwrap_or_default().into(),
                    z_range: (0, 0),
                    grid: Arc::new(half),
                    present,
                    expected: side_parents
                        .map(|p| parents.contains(&p) && self.refiner.is_refinable(p)),
                    refined: None,
                    class: None,
                    bound_class: None,
                    bound_profile: None,
                    colour: colour_half
                        .and_then(|(grids, _)| layer_node(self.colour.as_deref(), child, grids)),
                }
            }
        };
        self.insert_changed(node);
        Ok(())
    }

    /// Clears the half of `child` that lies in `parent` (the diagonal stays: the other
    /// half shares it); a child left with no half leaves the DAG.
    fn remove_half(&mut self, child: R::Id, parent: R::Id) {
        let side_parents = self.refiner.side_parents(child);
        let Some(h) = side_parents.iter().position(|&p| p == parent) else {
            return;
        };
        let Some(mut node) = self.nodes.remove(&child) else {
            return;
        };
        self.touched.insert(child);
        node.present[h] = false;
        if !node.present.iter().any(|p| *p) {
            return;
        }
        let keep = Half::BOTH[1 - h];
        let clear = |grid: &mut [i32], n: usize| {
            for i in 0..=n {
                for j in 0..=n {
                    if !keep.contains(i, j) {
                        grid[i * (n + 1) + j] = 0;
                    }
                }
            }
        };
        clear(
            Arc::make_mut(&mut node.grid).as_mut_slice(),
            self.refiner.n(),
        );
        if let (Some(layer), Some(c)) = (&self.colour, node.colour.as_mut()) {
            for g in Arc::make_mut(&mut c.grids).iter_mut() {
                clear(g, layer.n());
            }
        }
        self.insert_changed(node);
    }

    /// Stores a node whose grid or halves changed: new generation, its height range.
    fn insert_changed(&mut self, mut node: Node<R::Id>) {
        self.generations += 1;
        node.generation = self.generations;
        node.z_range = z_range(&node.grid, self.refiner.n(), node.present);
        self.touched.insert(node.id);
        self.nodes.insert(node.id, node);
    }

    /// Whether a half is in the cut: present in an unrefined diamond.
    pub fn in_cut(&self, id: R::Id, half: Half) -> bool {
        self.nodes
            .get(&id)
            .is_some_and(|n| n.refined.is_none() && n.has(half))
    }

    /// The halves that entered and left the cut since the previous call (the first call
    /// reports the whole cut as entered). Costs O(diamonds changed), not O(cut): the DAG
    /// notes each diamond it touches, and this compares just those with what it reported.
    /// One consumer (a renderer) should call it; [`Dag::restart_cut_changes`] makes the
    /// next call report the whole cut again.
    pub fn take_cut_changes(&mut self) -> CutChanges<R::Id> {
        let mut changes = CutChanges {
            entered: Vec::new(),
            left: Vec::new(),
        };
        let touched = std::mem::take(&mut self.touched);
        for id in touched {
            for half in Half::BOTH {
                let now = self.in_cut(id, half);
                let was = self.reported.contains(&(id, half));
                if now && !was {
                    self.reported.insert((id, half));
                    changes.entered.push((id, half));
                } else if was && !now {
                    self.reported.remove(&(id, half));
                    changes.left.push((id, half));
                }
            }
        }
        changes.entered.sort_unstable();
        changes.left.sort_unstable();
        changes
    }

    /// A half of the cut as a renderer takes it (`None` when the diamond is not here).
    pub fn patch(&self, id: R::Id, half: Half) -> Option<Patch<R::Id>> {
        let node = self.nodes.get(&id)?;
        Some(Patch {
            id,
            half,
            corners: node.corners,
            grid: Arc::clone(&node.grid),
            generation: node.generation,
            colour: node.colour.as_ref().map(|c| Arc::clone(&c.grids)),
        })
    }

    /// [`Dag::take_cut_changes`] with the patches that entered.
    pub fn take_patch_changes(&mut self) -> PatchChanges<R::Id> {
        let changes = self.take_cut_changes();
        let entered = changes
            .entered
            .into_iter()
            .filter_map(|(id, half)| self.patch(id, half))
            .collect();
        PatchChanges {
            entered,
            left: changes.left,
        }
    }

    /// Makes the next [`Dag::take_cut_changes`] report the whole cut as entered and
    /// nothing as left (for a consumer that dropped what it had).
    pub fn restart_cut_changes(&mut self) {
        self.reported.clear();
        self.touched = self.nodes.keys().copied().collect();
    }

    /// Halves in the cut (a counter: O(1)).
    pub fn cut_len(&self) -> usize {
        self.cut_halves
    }

    /// Refinements and coarsenings so far: equal counts mean an unchanged DAG.
    pub fn changes(&self) -> u64 {
        self.changes
    }

    /// The cut: every present half of every unrefined diamond, in a stable order.
    pub fn cut(&self) -> Vec<(R::Id, Half)> {
        let mut out: Vec<(R::Id, Half)> = self
            .nodes
            .values()
            .filter(|n| n.refined.is_none())
            .flat_map(|n| {
                Half::BOTH
                    .into_iter()
                    .filter(|h| n.has(*h))
                    .map(move |h| (n.id, h))
            })
            .collect();
        out.sort_unstable();
        out
    }

    /// Checks the cut: neighbouring halves agree bit for bit on every shared valid vertex,
    /// and every probe point of the domain ([`Domain::probes`]) lies in exactly one half.
    pub fn check_cut(&self) -> CutCheck {
        let n = self.refiner.n();
        let mut values: HashMap<[i64; 3], i32, std::hash::BuildHasherDefault<IdHasher>> =
            HashMap::default();
        let cut = self.cut();
        let mut check = CutCheck {
            counted_halves: self.cut_halves,
            ..CutCheck::default()
        };
        let mut triangles: HashMap<u8, Vec<[[f64; 2]; 3]>> = HashMap::new();
        for &(id, half) in &cut {
            check.halves += 1;
            let Some(node) = self.nodes.get(&id) else {
                continue;
            };
            if let Some((chart, t)) = self.refiner.half_triangle(&node.corners, half) {
                triangles.entry(chart).or_default().push(t);
            }
            let mask = self.refiner.info(id).and_then(|i| i.mask);
            edge_vertices(n, half, mask.as_ref(), |i, j| {
                let Some(pos) = self.refiner.vertex_point(id, &node.corners, i, j) else {
                    return;
                };
                let v = node.grid[i * (n + 1) + j];
                match values.insert(pos, v) {
                    Some(old) if old != v => check.cracks += 1,
                    Some(_) => check.shared_vertices += 1,
                    None => {}
                }
            });
        }
        check.colour_cracks = self.colour_cracks(&cut, &mut check.colour_shared);
        let probes = self.refiner.probes();
        let buckets: HashMap<u8, Buckets> = triangles
            .iter()
            .map(|(&chart, ts)| {
                let points = probes.iter().filter(|p| p.0 == chart).map(|p| p.1);
                (chart, Buckets::new(points, ts))
            })
            .collect();
        for (chart, p) in probes {
            let hits = match (triangles.get(&chart), buckets.get(&chart)) {
                (Some(ts), Some(b)) => b
                    .near(p)
                    .iter()
                    .filter(|&&k| in_triangle(p, &ts[k]))
                    .count(),
                _ => 0,
            };
            match hits {
                0 => check.uncovered += 1,
                1 => check.probes += 1,
                _ => check.overlaps += 1,
            }
        }
        check
    }
}

impl<R: Domain> Dag<R> {
    /// Colour edge vertices of the cut that neighbours disagree on (any channel); counts
    /// the agreeing ones in `shared`.
    fn colour_cracks(&self, cut: &[(R::Id, Half)], shared: &mut usize) -> usize {
        let Some(layer) = &self.colour else {
            return 0;
        };
        let n = layer.n();
        let mut values: HashMap<
            [i64; 3],
            [i32; CHANNELS],
            std::hash::BuildHasherDefault<IdHasher>,
        > = HashMap::default();
        let mut cracks = 0;
        let refiner = &layer.channels()[0];
        for &(id, half) in cut {
            let Some(colour) = self.nodes.get(&id).and_then(|n| n.colour.as_ref()) else {
                continue;
            };
            let corners = refiner.corners(colour.id);
            let mask = refiner.info(colour.id).and_then(|i| i.mask);
            edge_vertices(n, half, mask.as_ref(), |i, j| {
                let Some(pos) = refiner.vertex_point(colour.id, &corners, i, j) else {
                    return;
                };
                let k = i * (n + 1) + j;
                let v = [0, 1, 2].map(|c| colour.grids[c][k]);
                match values.insert(pos, v) {
                    Some(old) if old != v => cracks += 1,
                    Some(_) => *shared += 1,
                    None => {}
                }
            });
        }
        cracks
    }
}

/// Calls `f(i, j)` for each valid vertex of `half` of an `N`-grid that lies on an edge of
/// the half (the diamond's border or its diagonal): what neighbours share.
fn edge_vertices(
    n: usize,
    half: Half,
    mask: Option<&DiamondMask>,
    mut f: impl FnMut(usize, usize),
) {
    for i in 0..=n {
        for j in 0..=n {
            let on_edge = i == j || i == 0 || j == 0 || i == n || j == n;
            if on_edge && half.contains(i, j) && mask.is_none_or(|m| m.vertex(i, j)) {
                f(i, j);
            }
        }
    }
}

/// Two bound profiles of one diamond as one: the smaller class where both say, the
/// longer's where one does.
fn tighter_profile(a: Option<Arc<[u8]>>, b: &Arc<[u8]>) -> Arc<[u8]> {
    let Some(a) = a else {
        return b.clone();
    };
    let (long, short) = if a.len() >= b.len() { (&a, b) } else { (b, &a) };
    long.iter()
        .enumerate()
        .map(|(k, &c)| short.get(k).map_or(c, |&s| s.min(c)))
        .collect()
}

/// A refinement without its lattice (what a refined node keeps).
fn without_lattice<I>(r: Refined<I>) -> Refined<I> {
    Refined {
        vertices: Vec::new(),
        cells: Vec::new(),
        ..r
    }
}

/// A colour node for `child` (elevation id) with these grids.
fn layer_node<R: Domain>(
    layer: Option<&ColourLayer<R>>,
    child: R::Id,
    grids: Vec<Vec<i32>>,
) -> Option<ColourNode<R::Id>> {
    Some(ColourNode {
        id: layer?.colour_id(child)?,
        grids: Arc::new(grids),
        refined: None,
    })
}

/// Smallest and largest value of the present halves of a grid.
fn z_range(grid: &[i32], n: usize, present: [bool; 2]) -> (i32, i32) {
    let mut range = (i32::MAX, i32::MIN);
    for i in 0..=n {
        for j in 0..=n {
            let in_present = (present[0] && i >= j) || (present[1] && i <= j);
            if in_present {
                let v = grid[i * (n + 1) + j];
                range = (range.0.min(v), range.1.max(v));
            }
        }
    }
    if range.0 > range.1 { (0, 0) } else { range }
}

/// Triangles of one chart bucketed on a grid over the probes' extent by their bounding
/// boxes, so that a probe is tested against the triangles near it only.
struct Buckets {
    min: [f64; 2],
    cell: [f64; 2],
    cells: Vec<Vec<usize>>,
}

impl Buckets {
    const SIDE: usize = 64;

    fn new(points: impl Iterator<Item = [f64; 2]>, triangles: &[[[f64; 2]; 3]]) -> Buckets {
        let (mut min, mut max) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in points {
            for k in 0..2 {
                min[k] = min[k].min(p[k]);
                max[k] = max[k].max(p[k]);
            }
        }
        let cell = [0, 1].map(|k| ((max[k] - min[k]) / Self::SIDE as f64).max(1e-9));
        let mut b = Buckets {
            min,
            cell,
            cells: vec![Vec::new(); Self::SIDE * Self::SIDE],
        };
        if !(min[0].is_finite() && min[1].is_finite()) {
            return b;
        }
        for (k, t) in triangles.iter().enumerate() {
            let lo =
                [0, 1].map(|a| b.index(t.iter().map(|p| p[a]).fold(f64::INFINITY, f64::min), a));
            let hi = [0, 1]
                .map(|a| b.index(t.iter().map(|p| p[a]).fold(f64::NEG_INFINITY, f64::max), a));
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    b.cells[y * Self::SIDE + x].push(k);
                }
            }
        }
        b
    }

    /// The grid column (axis 0) or row (axis 1) of a coordinate, clamped to the grid.
    fn index(&self, v: f64, axis: usize) -> usize {
        let i = ((v - self.min[axis]) / self.cell[axis]).floor();
        i.clamp(0.0, (Self::SIDE - 1) as f64) as usize
    }

    /// The triangles whose boxes meet the cell of `p`.
    fn near(&self, p: [f64; 2]) -> &[usize] {
        &self.cells[self.index(p[1], 1) * Self::SIDE + self.index(p[0], 0)]
    }
}

/// Whether `p` is strictly inside triangle `t` (either orientation).
fn in_triangle(p: [f64; 2], t: &[[f64; 2]; 3]) -> bool {
    let side =
        |a: [f64; 2], b: [f64; 2]| (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]);
    let s = [side(t[0], t[1]), side(t[1], t[2]), side(t[2], t[0])];
    s.iter().all(|&x| x > 0.0) || s.iter().all(|&x| x < 0.0)
}

/// What [`Dag::check_cut`] found.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CutCheck {
    /// Halves in the cut.
    pub halves: usize,
    /// Halves in the cut by the DAG's counter ([`Dag::cut_len`]; must equal `halves`).
    pub counted_halves: usize,
    /// Edge vertices seen by more than one half, with equal values.
    pub shared_vertices: usize,
    /// Edge vertices seen by more than one half with different values (must be 0).
    pub cracks: usize,
    /// With a colour layer: colour edge vertices seen by more than one half, agreeing.
    pub colour_shared: usize,
    /// Colour edge vertices whose neighbours disagree in any channel (must be 0).
    pub colour_cracks: usize,
    /// Probe points of the raster covered by exactly one half.
    pub probes: usize,
    /// Probe points covered by no half (must be 0).
    pub uncovered: usize,
    /// Probe points covered by more than one half (must be 0).
    pub overlaps: usize,
}

impl CutCheck {
    /// No cracks, and the cut covers the raster exactly once.
    pub fn ok(&self) -> bool {
        self.cracks == 0
            && self.halves == self.counted_halves
            && self.colour_cracks == 0
            && self.uncovered == 0
            && self.overlaps == 0
            && self.probes > 0
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use quincunx_codec::encode::{
        CubeGrid, EncodeOptions, FromEncoded, Grid, RateMode, encode, encode_sphere,
    };
    use quincunx_decoder::incremental::SphereRefiner;

    fn options(n: usize) -> EncodeOptions {
        EncodeOptions {
            n,
            mode: RateMode::Lossless,
            sparse: false,
            rdo: Default::default(),
        }
    }

    fn height(a: f64, b: f64) -> f64 {
        (300.0 * (a * 0.05).sin() * (b * 0.07).cos() + 17.0 * ((a * b) % 5.0)).round()
    }

    /// Refines `steps` rounds of every refinable diamond with zero details.
    fn refine_some<R: Domain>(dag: &mut Dag<R>, steps: usize) {
        for _ in 0..steps {
            let ids: Vec<R::Id> = dag
                .nodes()
                .filter(|n| n.refined.is_none())
                .map(|n| n.id)
                .filter(|&id| dag.is_refinable(id))
                .collect();
            for id in ids {
                if dag.is_refinable(id) {
                    dag.refine(id, None).unwrap();
                }
            }
        }
    }

    /// A consistent cut checks out; a changed edge value is a crack, a removed half
    /// leaves probes uncovered, and a refined diamond whose lattice is dropped without
    /// coarsening (its children stay) overlaps them.
    fn check_cut_finds_what_is_wrong<R: Domain>(mut dag: Dag<R>) {
        refine_some(&mut dag, 3);
        let good = dag.check_cut();
        assert!(good.ok() && good.shared_vertices > 0, "{good:?}");

        let mut cracked = Dag {
            nodes: dag.nodes.clone(),
            ..Dag::new(Arc::clone(&dag.refiner))
        };
        let (id, _) = cracked.cut()[0];
        let node = cracked.nodes.get_mut(&id).unwrap();
        let mut grid = node.grid.to_vec();
        grid[0] += 1; // vertex (0, 0): a corner, shared with neighbours
        node.grid = Arc::new(grid);
        assert!(cracked.check_cut().cracks > 0);

        let mut holed = Dag {
            nodes: dag.nodes.clone(),
            ..Dag::new(Arc::clone(&dag.refiner))
        };
        let (id, _) = holed.cut()[holed.cut().len() / 2];
        holed.nodes.remove(&id);
        assert!(holed.check_cut().uncovered > 0);

        let mut doubled = Dag {
            nodes: dag.nodes.clone(),
            ..Dag::new(Arc::clone(&dag.refiner))
        };
        let refined = doubled
            .nodes
            .values()
            .find(|n| n.refined.is_some())
            .map(|n| n.id)
            .unwrap();
        doubled.nodes.get_mut(&refined).unwrap().refined = None;
        assert!(doubled.check_cut().overlaps > 0);
    }

    /// Replays random refinements and coarsenings; after each batch, the cut built from
    /// the reported changes equals the cut, and nothing is reported twice.
    fn cut_changes_follow_the_cut<R: Domain>(mut dag: Dag<R>, seed: u64) {
        use std::collections::BTreeSet;
        let mut state = seed;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as usize
        };
        let mut mirror: BTreeSet<(R::Id, Half)> = BTreeSet::new();
        let mut changes_seen = 0;
        for round in 0..60 {
            for _ in 0..1 + next() % 6 {
                let refinable: Vec<R::Id> = dag
                    .nodes()
                    .map(|n| n.id)
                    .filter(|&id| dag.is_refinable(id))
                    .collect();
                let coarsenable: Vec<R::Id> = dag
                    .nodes()
                    .map(|n| n.id)
                    .filter(|&id| dag.is_coarsenable(id))
                    .collect();
                let coarsen = round % 3 == 2 || refinable.is_empty() || dag.len() > 400;
                if coarsen && !coarsenable.is_empty() {
                    dag.coarsen(coarsenable[next() % coarsenable.len()])
                        .unwrap();
                } else if !refinable.is_empty() {
                    dag.refine(refinable[next() % refinable.len()], None)
                        .unwrap();
                }
            }
            let changes = dag.take_cut_changes();
            for key in &changes.left {
                assert!(mirror.remove(key), "{key:?} left without having entered");
            }
            for key in &changes.entered {
                assert!(mirror.insert(*key), "{key:?} entered twice");
            }
            changes_seen += changes.entered.len() + changes.left.len();
            let cut: BTreeSet<(R::Id, Half)> = dag.cut().into_iter().collect();
            assert_eq!(mirror, cut, "round {round}");
            assert!(dag.take_cut_changes().is_empty());
        }
        assert!(changes_seen > 100, "{changes_seen} changes");
        dag.restart_cut_changes();
        let again = dag.take_cut_changes();
        assert!(again.left.is_empty());
        assert_eq!(again.entered, dag.cut());
    }

    /// A 129 x 97 planar repository, N = 8, lossless.
    fn planar_refiner() -> Arc<PlanarRefiner> {
        let (w, h) = (129, 97);
        let grid = Grid {
            width: w,
            height: h,
            values_m: (0..w * h)
                .map(|k| height((k % w) as f64, (k / w) as f64))
                .collect(),
            quantum_m: Some(1.0),
        };
        let enc = encode(&grid, options(8)).unwrap();
        Arc::new(PlanarRefiner::from_encoded(&enc).unwrap())
    }

    /// A planet of face side 32, N = 8, lossless.
    fn sphere_refiner() -> Arc<SphereRefiner> {
        let face_side = 32;
        let w = face_side + 1;
        let cube = CubeGrid {
            face_side,
            values_m: (0..6 * w * w)
                .map(|k| height((k % w) as f64, (k / w) as f64))
                .collect(),
            quantum_m: Some(1.0),
        };
        let enc = encode_sphere(&cube, options(8)).unwrap();
        Arc::new(SphereRefiner::from_encoded(&enc).unwrap())
    }

    #[test]
    fn two_parents_profiles_keep_the_smaller_class_of_each_level() {
        let p = |v: &[u8]| Arc::<[u8]>::from(v);
        assert_eq!(&*tighter_profile(None, &p(&[5, 3])), &[5, 3]);
        assert_eq!(
            &*tighter_profile(Some(p(&[5, 3])), &p(&[4, 4, 2])),
            &[4, 3, 2]
        );
        assert_eq!(&*tighter_profile(Some(p(&[6, 1, 1])), &p(&[7])), &[6, 1, 1]);
        assert_eq!(&*tighter_profile(Some(p(&[])), &p(&[2])), &[2]);
    }

    #[test]
    fn cut_changes_follow_the_cut_on_the_plane_and_a_planet() {
        let (planar, sphere) = (planar_refiner(), sphere_refiner());
        for seed in 0..4 {
            cut_changes_follow_the_cut(Dag::new(Arc::clone(&planar)), seed);
            cut_changes_follow_the_cut(Dag::new(Arc::clone(&sphere)), seed);
        }
    }

    #[test]
    fn check_cut_finds_cracks_holes_and_overlaps_on_the_plane() {
        check_cut_finds_what_is_wrong(Dag::new(planar_refiner()));
    }

    #[test]
    fn check_cut_finds_cracks_holes_and_overlaps_on_a_planet() {
        check_cut_finds_what_is_wrong(Dag::new(sphere_refiner()));
    }
}
