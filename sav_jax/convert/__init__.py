"""Checkpoints: reading PyTorch files safely, key mapping, orbax, export.

    sd = load_state_dict("StereoAnyVideo_MIX.pth")   # no torch needed, no pickled code run
    variables = params_from_state_dict(sd, cfg)      # official names -> Flax variables
    sd2 = state_dict_from_params(variables)          # and back (exact round trip)
"""

from sav_jax.convert.orbax_io import (RANDOM_PRIOR, find_training_checkpoint,
                                      is_orbax_checkpoint, is_variables_checkpoint,
                                      random_prior_note, restore_variables, save_variables,
                                      untrained_note)
from sav_jax.convert.params import (export_state_dict, params_from_state_dict,
                                    state_dict_from_params)
from sav_jax.convert.torch_io import (CheckpointError, checkpoint_kind, load_checkpoint_object,
                                      load_state_dict, load_state_dict_of_kind, save_state_dict,
                                      unwrap_state_dict)
from sav_jax.convert.vda import vda_params_from_state_dict, vda_state_dict_from_params

__all__ = [
    "CheckpointError", "RANDOM_PRIOR", "checkpoint_kind", "export_state_dict", "find_training_checkpoint",
    "is_orbax_checkpoint", "is_variables_checkpoint", "load_checkpoint_object",
    "load_state_dict", "load_state_dict_of_kind", "params_from_state_dict", "random_prior_note",
    "restore_variables",
    "save_state_dict", "save_variables", "state_dict_from_params", "untrained_note",
    "unwrap_state_dict",
    "vda_params_from_state_dict", "vda_state_dict_from_params",
]

from sav_jax._lazy import submodule_getattr

__getattr__ = submodule_getattr(__name__)  # its other modules, on first use
