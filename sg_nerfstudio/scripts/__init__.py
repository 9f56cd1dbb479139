"""Console scripts (thin tyro wrappers around the library).

Importing this package (which every `sg-*` / `ns-register-meta` entry point does before its own imports) hides the
deprecation warnings that nerfstudio 1.1.5 and torch's own forward-mode AD raise under the torch this project runs on
(`torch.jit.script`, `torch.cuda.amp.custom_fwd/bwd`, websockets' renamed modules): six lines before every command's
first output that a user can do nothing about. Library callers who import `sg_nerfstudio` directly keep them.
"""

import warnings

for _message in (r"`torch\.jit\.script` is deprecated", r"`torch\.cuda\.amp\.custom_(fwd|bwd)\(args\.\.\.\)` is deprecated"):
    warnings.filterwarnings("ignore", message=_message, category=FutureWarning)
warnings.filterwarnings("ignore", message=r"websockets\.", category=DeprecationWarning)
