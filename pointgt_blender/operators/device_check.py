"""Operators that need PyTorch share `NeedsTorch.poll`; the device check is the first of them."""
import bpy

from ..bridge import deps
from ..ui.properties import poll_active_model


class NeedsTorch:
    """Mixin: poll() fails with the reason until `import torch` works."""

    @classmethod
    def poll(cls, context):
        status = deps.torch_status()
        if not status.available:
            cls.poll_message_set(status.message)
            return False
        return True


def device_problem(device: str) -> str:
    """'' when torch can run on `device` ('CPU' / 'CUDA'), else what to change."""
    import torch

    if device == 'CUDA' and not torch.cuda.is_available():
        return (f"CUDA is not available to PyTorch {torch.__version__} (CPU build or no NVIDIA GPU); "
                f"set the model's Device to CPU")
    return ""


class POINTGT_OT_check_device(NeedsTorch, bpy.types.Operator):
    """Check that PyTorch can run the model on the chosen device"""
    bl_idname = "pointgt.check_device"
    bl_label = "Check Device"
    bl_options = {'REGISTER'}

    @classmethod
    def poll(cls, context):
        return poll_active_model(cls, context) and super().poll(context)

    def execute(self, context):
        device = context.active_object.pointgt.device
        try:
            import torch

            problem = device_problem(device)
        except Exception as exc:
            self.report({'ERROR'}, f"PyTorch failed: {type(exc).__name__}: {exc}")
            return {'CANCELLED'}
        if problem:
            self.report({'ERROR'}, problem)
            return {'CANCELLED'}
        self.report({'INFO'}, f"PyTorch {torch.__version__} runs on {device}")
        return {'FINISHED'}


CLASSES = (POINTGT_OT_check_device,)
