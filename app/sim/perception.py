"""Realistic perception: a segmenter whose errors look like a real one's, and a robot that does not know its
segmenter's true rates.

The idealised model (`app.sim.noise.LabelNoise`) flips every observed voxel independently with exactly the
rates the service's vision update assumes. A real segmenter (a 2-D instance or semantic segmenter whose
labels are projected into the voxels through depth, as in Hydra) fails otherwise:

- its errors are per *object per frame*: an object seen in a frame is labelled as one class, rightly or
  wrongly, not voxel by voxel; and the same object tends to get the same answer from frame to frame (its
  appearance does not change), so its frames are correlated too;
- it misses what looks small: recall falls with the object's apparent size, hence with distance, and a
  partly hidden object is judged by the part that shows;
- its false positives are mostly whole look-alike objects (a towel called a backpack), few scattered pixels;
- and the rates a robot is configured with are not the rates it meets.

The model. Let T be the target's class, a the accuracy, s the look-alike share, rho the frame correlation,
r_max, A_50 and k the recall curve's parameters, epsilon the speckle rate and m the mis-specification factor
(`PerceptionConfig`). Once per episode every object o of the world draws a propensity to be called T:

    theta_o ~ Beta(mu_o kappa, (1 - mu_o) kappa),   kappa = 1/rho - 1                              (1)
    mu_o = a                    for an object of class T (the target, and mapped objects of its class)
    mu_o = (1 - a) s w_o        for any other object, w_o its look-alike weight (6)

so E[theta_o] = mu_o and two frames of one object agree (given detection) with correlation rho; rho = 0 gives
every frame its own independent draw at mu_o, rho = 1 one answer per object for the whole episode.

The robot's map lacks the target (that is why it asks), and the map was built by the same kind of segmenter:
an object in view while mapping and absent from the map went unlabelled every time it was seen. With the
`mapping_pass` "route" the robot mapped the room along the same route before: the target was in view in the
frames F in which the episode's camera sees it, at the same apparent sizes, and called T in none of them, so
its propensity is drawn from its posterior given those misses (r_f = r(A_f), equation (2)):

    p(theta | missed in F) ∝ Beta(theta; mu kappa, (1 - mu) kappa) prod_{f in F} (1 - r_f theta)      (1')

sampled exactly by rejection (a draw of (1) is kept with probability prod (1 - r_f theta)). A target never
in view has F empty and keeps (1) (it is missing from the map because it was never seen), as do the mapped
objects of its class; "none" is a target put there after the map was built, the model before (1'), every
draw the same. With rho = 0 the frames are independent, past misses say nothing about the next frame, and
theta_target = mu; with rho = 1 theta is 1 with probability mu prod (1 - r_f) / (mu prod (1 - r_f) + 1 - mu).
With the defaults (a 0.8, rho 0.5) a target missed in 3 views at recall 0.9 has a mean propensity of 0.24
instead of 0.80; the dev rooms' observed targets are in view in 22 frames of 100 on average.

In each frame, every object o that n_o of the camera's rays stop on shows an apparent area of A_o = n_o P
pixels (P: pixels per ray, `pixels_per_ray`, of a real camera of `image_width_px` pixels across the same
field of view), and

    detected:  D_o ~ Bernoulli(r(A_o)),   r(A) = r_max A^k / (A^k + A_50^k)                       (2)
    called T:  C_o ~ Bernoulli(theta_o)   given D_o                                                (3)
    label:     T if D_o C_o; else, if D_o, its own class (class T: its most look-alike other class);
               else "unknown" (a pixel the segmenter leaves unlabelled)                            (4)

and every voxel of o observed in the frame takes that one label (the correlation within a frame). Then each
observed occupied voxel of another class than T reads T with probability epsilon (scattered false positives,
speckle), and free voxels read "free" (free space comes from depth, not from the segmenter):

    P(y = T | voxel of class T seen)  = r(A) theta_o           (mean over objects: r(A) a)         (5)
    P(y = T | other voxel seen)      ~= r(A) theta_o + epsilon (mean: r(A) (1 - a) s w_o + epsilon)

Partial views enter twice: the camera labels only the surface its rays reach (`app.sim.camera`), and A_o
counts only the rays that reach o, so a half-hidden object is as hard to find as one of half its size.

Look-alike weight of an object of class c for the target class T (1 for a looser naming of T, as the
vocabulary defines it: the same head noun, "coffee table" for "table", or a generic word covering both):

    w_o = 1                                               if lexical_match(c, T) = 1              (6)
    w_o = exp(-|| log e_o - log e_target ||^2 / tau^2)    otherwise

where e are the box extents sorted in decreasing order (shape and size without orientation) and tau the
shape scale: an object twice as large along one axis as the target has w = e^-1 with tau = log 2.

Sensor model. The service is told (tp_s, fp_s) for the rates (tp*, fp*) the segmenter really has:

    1 - tp_s = (1 - tp*) / m,    fp_s = fp* / m                                                   (7)

m = 1 is a robot that knows its rates (still wrong about their independence), m > 1 one that believes its
segmenter makes m times fewer errors than it does. (tp*, fp*) are `CALIBRATED_RATES`, the voxel rates (5)
measured over training rooms (see the constant); every run also reports the rates it realised, so the factor
actually met is on record (`RateCounts`).

Defaults and where they come from (`PerceptionConfig`):

- `image_width_px` 640: ScanNet's depth frames are 640 x 480 (Dai et al., "ScanNet", CVPR 2017), and the
  camera's 90 x 60 degree field of view is about a RealSense D435's depth field of view (87 x 58 degrees).
  With the camera's 64 x 48 rays one ray stands for 10 x 7.7 = 77 pixels.
- `half_recall_area_px` 1024 = 32^2 and `recall_slope` 1: 32^2 pixels is COCO's boundary between small and
  medium objects (Lin et al., "Microsoft COCO", ECCV 2014), and detectors find small objects about a third
  as well as large ones (Mask R-CNN, ResNeXt-101-FPN: mask AP 16.9 on small objects against 53.5 on large;
  He et al., ICCV 2017, Table 1). With (2), 16^2 px is found at 0.2 r_max, 32^2 at 0.5 r_max, 96^2 (COCO's
  "large") at 0.9 r_max; a 10 cm object at 4 m (8 x 8 px) at 0.06 r_max, i.e. rarely. The slope is an
  assumption (the curve's exact shape is not published in this form).
- `max_recall` 0.9: assumption: a large, fully visible object of a known class is segmented in 9 frames of 10
  (motion blur, exposure and odd views take the rest).
- `accuracy` 0.8: assumption: a detected object of the target's class is given the right class 4 times in
  5. The realised class-level precision, recall and IoU of every run are reported (`RateCounts`), to be
  compared with published per-class IoUs of indoor segmenters.
- `lookalike_share` 0.5 and `shape_scale` log 2: assumption: at most half of an object's misclassifications
  go to any one other class, and look-alikes are of similar shape and size. That confusions with similar
  classes are one of the main kinds of false positive is Hoiem et al.'s finding ("Diagnosing error in object
  detectors", ECCV 2012); the weights' form is ours.
- `frame_correlation` 0.5: assumption: an object's appearance, hence the segmenter's answer, is much the same
  from frame to frame but not identical (the flicker that video detectors smooth out); 0.5 is half way
  between independent frames and one answer per episode.
- `speckle` 0.002: assumption: scattered false-positive voxels an order of magnitude rarer than a look-alike's
  whole-object ones (about 0.05 per frame for w = 1).
- `mapping_pass` "route": the premise of the service (the map lacks the target) made consistent with the
  segmenter that built the map; no parameter to choose. "none" gives the earlier tables.
- `misspecification` 1.5: ImageNet classifiers lose 11-14 points of accuracy on a new test set collected the
  same way as the benchmark's (Recht et al., "Do ImageNet classifiers generalize to ImageNet?", ICML 2019):
  for a model 75% accurate on the benchmark, about 1.5 times the errors it was measured with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.errors import InvalidInput
from app.sim.camera import CameraConfig, Observation
from app.sim.noise import UNKNOWN_LABEL
from app.sim.world import FREE, FREE_LABEL, SemanticVoxelWorld
from app.vocabulary import class_key, lemmas, lexical_match

#: (tp*, fp*): the voxel rates (5) of the default model, measured over the frames of 200 episodes in training
#: rooms (human descriptions of the training scans, `vlmap data referring ... --out data/human/train.jsonl`,
#: then `vlmap sim --scenes data/human/train.jsonl --episodes 200 --steps 100 --seed 0 --measure-rates --out
#: DIR`: 8.66 M occupied-voxel observations; the target class's precision 0.82, IoU 0.58; 2026-12-02; two
#: draws of 50 episodes gave (0.595, 0.0076) and (0.662, 0.0104)). tp* counts the voxels of objects of the
#: target's class, fp* the occupied voxels of other classes. Never measured on validation rooms: a robot
#: calibrates its segmenter where it was developed. Measured without (1') (before it existed; now add
#: `--mapping-pass none`): a segmenter's rates are measured on objects in general, not on those a map missed.
CALIBRATED_RATES = (0.662, 0.0077)

PERCEPTION_MODELS = ("realistic", "ideal")
#: How the sought target came to be missing from the map: (1') along the episode's route, or not at all.
MAPPING_PASSES = ("route", "none")


@dataclass(frozen=True)
class PerceptionConfig:
    """Parameters of the realistic segmenter (module docstring: equations and where each default comes
    from)."""

    image_width_px: int = 640
    max_recall: float = 0.9
    half_recall_area_px: float = 1024.0
    recall_slope: float = 1.0
    accuracy: float = 0.8
    lookalike_share: float = 0.5
    shape_scale: float = math.log(2.0)
    frame_correlation: float = 0.5
    speckle: float = 0.002
    mapping_pass: str = "route"
    misspecification: float = 1.5
    true_rates: tuple[float, float] = CALIBRATED_RATES

    def __post_init__(self) -> None:
        probabilities = {
            "max_recall": self.max_recall,
            "accuracy": self.accuracy,
            "lookalike_share": self.lookalike_share,
            "frame_correlation": self.frame_correlation,
            "speckle": self.speckle,
        }
        for name, value in probabilities.items():
            if not (math.isfinite(value) and 0.0 <= value <= 1.0):
                msg = f"{name} must be a probability in [0, 1], got {value}"
                raise InvalidInput(msg, f"perception.{name}")
        positives = {
            "half_recall_area_px": self.half_recall_area_px,
            "recall_slope": self.recall_slope,
            "shape_scale": self.shape_scale,
            "misspecification": self.misspecification,
        }
        for name, value in positives.items():
            if not (math.isfinite(value) and value > 0.0):
                msg = f"{name} must be a positive number, got {value}"
                raise InvalidInput(msg, f"perception.{name}")
        if self.mapping_pass not in MAPPING_PASSES:
            msg = f"mapping_pass must be one of {', '.join(MAPPING_PASSES)}, got {self.mapping_pass!r}"
            raise InvalidInput(msg, "perception.mapping_pass")
        if self.image_width_px < 1:
            msg = f"image_width_px must be at least 1, got {self.image_width_px}"
            raise InvalidInput(msg, "perception.image_width_px")
        misspecify(*self.true_rates, self.misspecification)  # validates the rates and the factor together

    @property
    def sensor_model(self) -> tuple[float, float]:
        """(tp_s, fp_s) the service is told: equation (7) applied to `true_rates`."""
        return misspecify(*self.true_rates, self.misspecification)


def misspecify(tp: float, fp: float, factor: float) -> tuple[float, float]:
    """Equation (7): the rates a robot believes when its segmenter makes `factor` times the errors it was
    told, 1 - tp_s = (1 - tp) / factor and fp_s = fp / factor. InvalidInput unless 0 < fp_s < tp_s < 1."""
    if not (math.isfinite(factor) and factor > 0):
        msg = f"the mis-specification factor must be a positive number, got {factor}"
        raise InvalidInput(msg, "perception.misspecification")
    told = (1.0 - (1.0 - tp) / factor, fp / factor)
    if not (0.0 < told[1] < told[0] < 1.0):
        msg = (
            f"rates tp={tp}, fp={fp} with factor {factor} give tp_s={told[0]:.4g}, fp_s={told[1]:.4g}; "
            "need 0 < fp_s < tp_s < 1"
        )
        raise InvalidInput(msg, "perception.true_rates")
    return told


def pixels_per_ray(camera: CameraConfig, image_width_px: int) -> float:
    """Pixels of a real camera, `image_width_px` wide with square pixels and the same field of view, that
    one of the camera's rays stands for: (W_px / w) (2 f tan(vfov/2) / h), f = W_px / (2 tan(hfov/2)) (the
    rays are evenly spaced on the image plane, so every ray covers the same area)."""
    focal = image_width_px / (2.0 * math.tan(math.radians(camera.hfov_deg) / 2.0))
    return (
        (image_width_px / camera.width)
        * (2.0 * focal * math.tan(math.radians(camera.vfov_deg) / 2.0))
        / (camera.height)
    )


def recall(area_px: np.ndarray | float, config: PerceptionConfig) -> np.ndarray:
    """Equation (2): r(A) = r_max A^k / (A^k + A_50^k), elementwise; 0 for A = 0."""
    area = np.asarray(area_px, dtype=np.float64)
    ratio = (config.half_recall_area_px / np.maximum(area, 1e-300)) ** config.recall_slope
    return np.where(area > 0, config.max_recall / (1.0 + ratio), 0.0)


def shape_similarity(sizes: np.ndarray, target_size: np.ndarray, scale: float) -> np.ndarray:
    """The second case of equation (6): exp(-||log e - log e_target||^2 / tau^2), e the extents sorted in
    decreasing order; (n,) for (n, 3) sizes."""
    e = -np.sort(-np.maximum(np.asarray(sizes, dtype=np.float64).reshape(-1, 3), 1e-3), axis=1)  # (n, 3)
    t = -np.sort(-np.maximum(np.asarray(target_size, dtype=np.float64).reshape(3), 1e-3))  # (3,)
    gap = np.sum((np.log(e) - np.log(t)) ** 2, axis=1)
    similarity: np.ndarray = np.exp(-gap / scale**2)
    return similarity


def lookalike_weights(
    labels: list[str] | tuple[str, ...],
    sizes: np.ndarray,
    target_label: str,
    target_size: np.ndarray,
    scale: float,
) -> np.ndarray:
    """Equation (6) for every object: (n,) weights in [0, 1]; objects of the target's class get 1 (they are
    not look-alikes but the class itself; callers treat them apart)."""
    target_lemmas = lemmas(target_label)
    target_key = class_key(target_label)
    weights = shape_similarity(sizes, target_size, scale)
    for k, label in enumerate(labels):
        if class_key(label) == target_key or lexical_match(lemmas(label), target_lemmas) == 1:
            weights[k] = 1.0
    return weights


def propensities(mean: np.ndarray, correlation: float, rng: np.random.Generator) -> np.ndarray:
    """Equation (1): theta ~ Beta(mu kappa, (1 - mu) kappa), kappa = 1/rho - 1, elementwise for (n,) means;
    theta = mu for rho = 0 (no draw), theta ~ Bernoulli(mu) for rho = 1."""
    mu = np.clip(np.asarray(mean, dtype=np.float64), 0.0, 1.0)
    if correlation <= 0.0:
        return mu.copy()
    if correlation >= 1.0:
        return (rng.random(len(mu)) < mu).astype(np.float64)
    kappa = 1.0 / correlation - 1.0
    inside = (mu > 0.0) & (mu < 1.0)
    theta = mu.copy()
    theta[inside] = rng.beta(mu[inside] * kappa, (1.0 - mu[inside]) * kappa)
    return theta


def unmapped_propensity(
    mean: float, correlation: float, recalls: np.ndarray, rng: np.random.Generator
) -> float:
    """Equation (1'): theta of an object of mean propensity `mean` that went unlabelled in views of recall
    `recalls` (r(A_f), one per view), drawn from Beta(mu kappa, (1 - mu) kappa) prod (1 - r_f theta) by
    rejection in batches of draws of (1). No view: one draw of (1) (the same draw as `propensities`); rho = 0
    or mu in {0, 1}: theta = mu (a point mass stays one); rho = 1: the Bernoulli posterior, drawn once."""
    r = np.asarray(recalls, dtype=np.float64)
    if len(r) == 0:
        return float(propensities(np.array([mean]), correlation, rng)[0])
    if correlation <= 0.0 or mean <= 0.0 or mean >= 1.0:
        return float(np.clip(mean, 0.0, 1.0))
    if correlation >= 1.0:
        missed_if_one = math.exp(float(np.sum(np.log1p(-np.minimum(r, 1.0 - 1e-12)))))  # prod (1 - r_f)
        odds_one = mean * missed_if_one / (1.0 - mean)
        return float(rng.random() < odds_one / (1.0 + odds_one))
    batch = 4096
    for _ in range(10_000):
        theta = propensities(np.full(batch, mean), correlation, rng)
        accept = np.exp(np.sum(np.log1p(-np.outer(theta, r)), axis=1))  # (batch,)
        kept = np.flatnonzero(rng.random(batch) < accept)
        if len(kept):
            return float(theta[kept[0]])
    msg = (
        f"no propensity drawn for an object missed in {len(r)} views (mean {mean}, correlation "
        f"{correlation}): such misses are too unlikely under the segmenter's parameters; use mapping_pass "
        "'none'"
    )
    raise InvalidInput(msg, "perception.mapping_pass")


class Segmenter:
    """The realistic segmenter of one episode: the world's objects, their look-alike weights (6) and their
    propensities (1), drawn once from `rng` at construction; `miss_while_mapping` redraws the sought target's
    by (1'); `labels` labels one frame (2)-(5)."""

    def __init__(
        self,
        config: PerceptionConfig,
        world: SemanticVoxelWorld,
        target_label: str,
        target_size: np.ndarray,
        camera: CameraConfig,
        rng: np.random.Generator,
    ) -> None:
        self.config = config
        self.target_label = target_label
        target_key = class_key(target_label)
        labels = list(world.labels)
        sizes = np.array([o.size for o in world.objects], dtype=np.float64)  # (n, 3) unrotated extents
        #: (n,) bool: the object is of the target's class.
        self.is_target_class = np.array([class_key(label) == target_key for label in labels], dtype=bool)
        #: (n,) look-alike weights, equation (6).
        self.weights = lookalike_weights(labels, sizes, target_label, target_size, config.shape_scale)
        others = (1.0 - config.accuracy) * config.lookalike_share * self.weights
        #: (n,) mu_o of equation (1).
        self.mean = np.where(self.is_target_class, config.accuracy, others)
        #: (n,) theta_o of equation (1), fixed for the episode.
        self.theta = propensities(self.mean, config.frame_correlation, rng)
        self.pixels_per_ray = pixels_per_ray(camera, config.image_width_px)
        # What a target-class object is called when detected but not as T: its most look-alike other class.
        candidates = np.flatnonzero(~self.is_target_class)
        confusion = labels[int(candidates[np.argmax(self.weights[candidates])])] if len(candidates) else None
        # Label codes: objects' own labels, then T, "unknown", "free" (a voxel's label is a code into this).
        self._names = np.array([*labels, target_label, UNKNOWN_LABEL, FREE_LABEL])
        n = len(labels)
        self._code_t, self._code_unknown, self._code_free = n, n + 1, n + 2
        own = np.arange(n)
        self._code_rejected = np.where(
            self.is_target_class, labels.index(confusion) if confusion is not None else n + 1, own
        )  # (n,) the label code of a detected object not called T

    def frame_objects(self, observation: Observation) -> tuple[np.ndarray, np.ndarray]:
        """(codes, areas): the objects some ray stopped on in the frame, in increasing code order, and their
        apparent areas A_o = n_o P in pixels."""
        hits = observation.ray_owner[observation.ray_owner != FREE]
        if len(observation.flat_idx) and len(observation.ray_owner) == 0:
            msg = "the realistic segmenter needs the observation's rays (Camera.observe records them)"
            raise ValueError(msg)
        codes, counts = np.unique(hits, return_counts=True)
        return codes.astype(np.int64), counts * self.pixels_per_ray

    def view_recalls(self, observations: list[Observation], index: int) -> np.ndarray:
        """r(A_f) of object `index` in each of the frames that show it: (|F|,)."""
        out = []
        for observation in observations:
            codes, areas = self.frame_objects(observation)
            at = np.searchsorted(codes, index)
            if at < len(codes) and codes[at] == index:
                out.append(float(recall(float(areas[at]), self.config)))
        return np.array(out, dtype=np.float64)

    def miss_while_mapping(
        self, index: int, observations: list[Observation], rng: np.random.Generator
    ) -> None:
        """Equation (1') with the `mapping_pass` "route": object `index` (the target the map lacks) went
        unlabelled in every frame of `observations` that shows it; redraws its propensity from `rng` (no
        draw when no frame shows it, or with "none")."""
        if self.config.mapping_pass == "none":
            return
        recalls = self.view_recalls(observations, index)
        if len(recalls):
            self.theta[index] = unmapped_propensity(
                float(self.mean[index]), self.config.frame_correlation, recalls, rng
            )

    def label_codes(self, observation: Observation, rng: np.random.Generator) -> np.ndarray:
        """(M,) label codes of the observed voxels (names: `names`), equations (2)-(5).

        Draws 2 uniforms per object in view (detection, class) and one per occupied voxel (speckle), so the
        stream of an episode depends only on its frames.
        """
        codes, areas = self.frame_objects(observation)
        u_detect = rng.random(len(codes))
        u_class = rng.random(len(codes))
        detected = u_detect < recall(areas, self.config)
        called_t = detected & (u_class < self.theta[codes])
        object_label = np.where(
            called_t, self._code_t, np.where(detected, self._code_rejected[codes], self._code_unknown)
        )
        # Every voxel of an object takes its object's label (the per-object correlation).
        owner = observation.owner.astype(np.int64)
        occupied = owner != FREE
        out = np.full(len(owner), self._code_free, dtype=np.int64)
        position = np.searchsorted(codes, owner[occupied])
        out[occupied] = object_label[position]
        # Speckle: scattered false positives on occupied voxels of other classes.
        u_speckle = rng.random(int(occupied.sum()))
        flips = (u_speckle < self.config.speckle) & ~self.is_target_class[owner[occupied]]
        occupied_idx = np.flatnonzero(occupied)
        out[occupied_idx[flips]] = self._code_t
        return out

    @property
    def names(self) -> np.ndarray:
        """Label names of the codes `label_codes` returns."""
        return self._names

    def labels(self, observation: Observation, rng: np.random.Generator) -> np.ndarray:
        """(M,) label names of the observed voxels."""
        names: np.ndarray = self._names[self.label_codes(observation, rng)]
        return names


@dataclass
class RateCounts:
    """Counts of one run's observed voxels by truth and label, for the rates it realised (5): voxels of the
    target's class and how many read T, occupied voxels of other classes and how many read T; and frames in
    which the target itself was in view, and in how many any of its voxels read T."""

    target_class_voxels: int = 0
    target_class_as_t: int = 0
    other_voxels: int = 0
    other_as_t: int = 0
    target_frames: int = 0
    target_frames_as_t: int = 0

    def add(self, other: RateCounts) -> None:
        for name in self.__dataclass_fields__:
            setattr(self, name, getattr(self, name) + getattr(other, name))

    def count(self, is_target_class: np.ndarray, says_t: np.ndarray, is_target: np.ndarray) -> None:
        """Add one frame: (M,) per occupied observed voxel, whether it is of the target's class, whether it
        reads T, whether it is the target's own."""
        self.target_class_voxels += int(is_target_class.sum())
        self.target_class_as_t += int((is_target_class & says_t).sum())
        self.other_voxels += int((~is_target_class).sum())
        self.other_as_t += int((~is_target_class & says_t).sum())
        if is_target.any():
            self.target_frames += 1
            self.target_frames_as_t += int((is_target & says_t).any())

    def summary(self) -> dict[str, float | int | None]:
        """tp = P(T | target-class voxel), fp = P(T | other occupied voxel), the target class's precision,
        recall and IoU over voxel observations, and the share of the target's frames that labelled it T."""

        def ratio(a: int, b: int) -> float | None:
            return a / b if b else None

        tp_count, fp_count = self.target_class_as_t, self.other_as_t
        fn_count = self.target_class_voxels - tp_count
        return {
            "tp": ratio(tp_count, self.target_class_voxels),
            "fp": ratio(fp_count, self.other_voxels),
            "precision": ratio(tp_count, tp_count + fp_count),
            "recall": ratio(tp_count, self.target_class_voxels),
            "iou": ratio(tp_count, tp_count + fp_count + fn_count),
            "target_frames": self.target_frames,
            "target_frames_labelled_t_pct": None
            if not self.target_frames
            else 100.0 * self.target_frames_as_t / self.target_frames,
            "voxels": self.target_class_voxels + self.other_voxels,
        }
