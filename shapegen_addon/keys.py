"""Every `shapegen_*` custom-property key ShapeGen writes into a .blend, by datablock.

This module owns the names (and says what each holds); the formats built from them are
written and read in one module each: `prepared` (prepared collections and shape objects,
their correspondence), `latent` (objects tagged with a latent vector, the live object),
`store` (the Text datablock holding the model), `exclusion` (objects left out of training).
Some keys sit on several datablocks
(`MODEL_ID_KEY`, `TEMPLATE_KEY`): the comment says where.
"""

from __future__ import annotations

# ------------------------------------------------------------------ the model's Text datablock
MODEL_FILE_KEY = "shapegen_model_npz"  # bytes: the model .npz file, byte for byte
MODEL_ID_KEY = "shapegen_model_id"  # uuid of the model; also on tagged objects and the latent-map image
MODEL_NAME_KEY = "shapegen_model_name"  # the model's name (the fitted collection's)
# summary, so panels draw without decoding the model
MODEL_TYPE_KEY = "shapegen_model_type"  # "ppca", "gplvm" or "bgplvm"
LATENT_DIM_KEY = "shapegen_latent_dim"
N_SHAPES_KEY = "shapegen_n_shapes"
N_LANDMARKS_KEY = "shapegen_n_landmarks"
TEMPLATE_KEY = "shapegen_template"  # Text: the correspondence template; tagged object: the training shape it deforms
RESIDUAL_MEDIAN_KEY = "shapegen_residual_median"  # median correspondence residual, fraction of the diagonal
OUTLIERS_KEY = "shapegen_outliers"  # "name: reason" of every outlier shape
MATCHING_KEY = "shapegen_matching"  # which data term matched the landmarks (Correspondence.matching_summary)

# ------------------------------------------------------------------ a user's training collection
EXCLUDED_KEY = "shapegen_excluded"  # names of its objects Prepare, Find Correspondences and Fit leave out

# ------------------------------------------------------------------ a user's training object
KEEP_POSE_KEY = "shapegen_keep_pose"  # True: Prepare keeps its pose (never turned beyond the up axis; still flagged);
# also on its prepared copy: the flag it was prepared with (Fit reuses the copy only while they agree)

# ------------------------------------------------------------------ a prepared collection
PREPARED_KEY = "shapegen_prepared"  # True: made by Prepare
SOURCE_COLLECTION_KEY = "shapegen_source_collection"  # name of the user's collection it was prepared from
CORRESPONDENCE_TEMPLATE_KEY = "shapegen_correspondence_template"  # template of the last Find Correspondences
PREPARE_SETTINGS_KEY = "shapegen_prepare_settings"  # PrepareSettings it was made with, one JSON string


# ------------------------------------------------------------------ a prepared shape object
SOURCE_KEY = "shapegen_source"  # name of the user's original object
MESH_SOURCE_KEY = "shapegen_mesh_source"  # which mesh Prepare read: "evaluated" (modifiers applied) or "base"
TRANSFORM_KEY = "shapegen_transform"  # 16 floats, row-major: input (world) -> normalised frame
LANDMARKS_KEY = "shapegen_landmarks"  # flat float list (L*3), the object's local (normalised) frame
LANDMARK_FACES_KEY = "shapegen_landmark_faces"  # loop-triangle index of each landmark
LANDMARK_BARYCENTRIC_KEY = "shapegen_landmark_barycentric"  # flat (L*3) barycentrics in that triangle
LANDMARK_RADIUS_KEY = "shapegen_landmark_radius"  # exclusion radius of the landmark selection
POSE_CHANGE_KEY = "shapegen_pose_change"  # how and why Prepare turned it ("turned 180° about x: ..."); "": kept
FLAG_TURN_KEY = "shapegen_flag_turn"  # 9 floats, row-major: the turn its pose flag suggests (Turn Flagged); absent: none
POSE_ROTATION_KEY = "shapegen_pose_rotation"  # 9 floats, row-major: the turn Prepare applied after the up axis
POSE_OUTLIER_KEY = "shapegen_pose_outlier"  # why its pose looks wrong ("upside down relative to ..."); "": fine
CORRESPONDENCE_KEY = "shapegen_correspondence"  # flat (L*3) corresponded landmarks, object-local
CORRESPONDENCE_OUTLIER_KEY = "shapegen_correspondence_outlier"  # why it is an outlier of the correspondence ("": fits)


def mesh_source(evaluated: bool) -> str:
    """The MESH_SOURCE_KEY value of a copy read with or without modifiers."""
    return "evaluated" if evaluated else "base"


# ------------------------------------------------------------------ an object tagged with a latent vector
LATENT_KEY = "shapegen_latent"  # the latent vector (list of floats); with MODEL_ID_KEY and TEMPLATE_KEY
MODEL_KEY = "shapegen_model"  # the model's name
SEED_KEY = "shapegen_seed"  # a sample's seed (of the draw kept when the quality gate redrew it)
REJECTED_KEY = "shapegen_rejected"  # a sample: "seed S on TEMPLATE: reasons" of each mesh the quality gate refused
STIFFNESS_KEY = "shapegen_stiffness"  # a sample meshed stiffer than its model (quality gate): that final α
QUALITY_KEY = "shapegen_quality"  # the live object (and one baked from it): why its mesh fails the quality gate ("": passes)
INTERPOLATION_KEY = "shapegen_interpolation"  # an in-between shape's position t in [0, 1]
LIVE_KEY = "shapegen_live"  # the live object: id of the model whose sliders drive it
TEMPLATE_INDEX_KEY = "shapegen_template_index"  # the live object: index of its template shape
VERTEX_MAP_KEY = "shapegen_vertex_map"  # the live object: core template vertex of each mesh vertex (absent: identity)

# ------------------------------------------------------------------ the latent-map image (and MODEL_ID_KEY)
MAP_DIMS_KEY = "shapegen_dims"  # latent dimensions on x and y
MAP_BOUNDS_KEY = "shapegen_bounds"  # x0, x1, y0, y1 of the drawn latent window

# ---- pins of the live object (pins.py)
PIN_KEY = "shapegen_pin"  # a pin (Empty): the landmark index it pins; with MODEL_ID_KEY
PIN_DISTANCE_KEY = "shapegen_pin_distance"  # a pin: how far the live object stays from it (object units)
PINS_START_KEY = "shapegen_pins_start"  # the live object: its latent vector before the first pin (Clear Pins restores it)
STD_ATTRIBUTE = "shapegen_std"  # the live object's colour attribute: posterior std per vertex (Show Uncertainty)
